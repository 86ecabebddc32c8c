"""The installed ``logsph-trace`` entry point, run as a user would, in a subprocess."""

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import logsph_trace as lt

REPO = Path(__file__).resolve().parents[1]


def _entry_point():
    found = Path(sys.executable).parent / "logsph-trace"
    return str(found) if found.exists() else shutil.which("logsph-trace")


def run(*args, cwd=None):
    command = _entry_point()
    assert command, "the logsph-trace entry point is not installed (pip install -e .)"
    env = dict(os.environ, MPLBACKEND="Agg")
    return subprocess.run([command, *args], capture_output=True, text=True, cwd=cwd or REPO,
                          env=env, timeout=600)


def test_trace_one_ray_in_each_format():
    args = ["trace", "--origin", "0", "20", "20", "--direction", "-0.3", "-0.01", "0",
            "--spacing", "paper"]
    table = run(*args)
    assert table.returncode == 0, table.stderr
    assert len(table.stdout.strip().splitlines()) == 1 + 14  # header + the 14 cells of Fig. 3
    rows = json.loads(run(*args, "--format", "json").stdout)
    grid = lt.Grid.from_increments(10.0, 80.0, 10, d_theta=10.0, d_phi=10.0)
    want = lt.trace(grid, [0, 20, 20], [-0.3, -0.01, 0])
    assert [[r["i"], r["j"], r["k"]] for r in rows] == want.cells.tolist()
    csv = run(*args, "--format", "csv").stdout.splitlines()
    assert csv[0] == "i,j,k,t_enter,t_exit" and len(csv) == 15


def test_grid_spec():
    result = run("trace", "--grid", "0.3,10,16,36,18", "--origin", "0.4", "1.5", "1.2",
                 "--direction", "-0.1", "-0.4", "1", "--format", "json")
    assert result.returncode == 0, result.stderr
    want = lt.trace(lt.Grid(0.3, 10, 16, 36, 18), [0.4, 1.5, 1.2], [-0.1, -0.4, 1])
    assert [[r["i"], r["j"], r["k"]] for r in json.loads(result.stdout)] == want.cells.tolist()
    bad = run("trace", "--grid", "0.3,10,16", "--origin", "0", "0", "1",
              "--direction", "0", "0", "1")
    assert bad.returncode == 2 and "--grid takes RHO_MIN,RHO_MAX" in bad.stderr
    bad = run("trace", "--grid", "0.3,10,16,36,18,cubic", "--origin", "0", "0", "1",
              "--direction", "0", "0", "1")
    assert bad.returncode == 2 and "spacing must be one of" in bad.stderr


def test_trace_a_cone():
    result = run("trace", "--origin", "0", "20", "20", "--direction", "-0.3", "-0.01", "0",
                 "--cone", "5", "--format", "json")
    assert result.returncode == 0, result.stderr
    rows = json.loads(result.stdout)
    assert abs(sum(r["weight"] for r in rows) - 1.0) < 1e-9


@pytest.mark.parametrize("suffix", [".npy", ".csv"])
def test_trace_a_batch_file(tmp_path, suffix):
    rng = np.random.default_rng(71)
    rays = np.hstack([rng.uniform(-90, 90, (500, 3)), rng.normal(size=(500, 3))])
    path = tmp_path / f"rays{suffix}"
    if suffix == ".npy":
        np.save(path, rays)
    else:
        np.savetxt(path, rays, delimiter=",", fmt="%.17g")
    out = tmp_path / "traces.npz"
    result = run("trace", "--rays", str(path), "--out", str(out), "--quiet", "--spacing", "paper")
    assert result.returncode == 0, result.stderr
    saved = np.load(out)
    grid = lt.Grid.from_increments(10.0, 80.0, 10, d_theta=10.0, d_phi=10.0)
    want = lt.trace_many(grid, rays)
    np.testing.assert_array_equal(saved["offsets"], want.offsets)
    np.testing.assert_array_equal(saved["cells"], want.cells)


@pytest.mark.parametrize(
    "args, message",
    [
        (["trace"], "give --origin X Y Z and --direction X Y Z, or --rays FILE"),
        (["trace", "--rays", "missing.npy", "--out", "x.npz"], "no such rays file"),
        (["trace", "--origin", "0", "0", "0", "--direction", "0", "0", "0"],
         "directions must be non-zero"),
        (["trace", "--origin", "0", "0", "0", "--direction", "1", "0", "0", "--rho", "80", "10"],
         "rho_min must be < rho_max"),
        (["trace", "--origin", "0", "0", "0", "--direction", "1", "0", "0", "--cone", "95"],
         "--cone must be a half-angle in [0, 90) degrees, got 95"),
        (["trace", "--origin", "0", "0"], "expected 3 arguments"),
        (["fly"], "invalid choice"),
    ],
)
def test_bad_arguments_are_one_line_and_exit_2(args, message):
    result = run(*args)
    assert result.returncode == 2
    assert message in result.stderr
    assert "Traceback" not in result.stderr


def test_bad_rays_file_shape(tmp_path):
    path = tmp_path / "rays.npy"
    np.save(path, np.zeros((4, 5)))
    result = run("trace", "--rays", str(path), "--out", str(tmp_path / "t.npz"))
    assert result.returncode == 2 and "must hold an (m, 6) array" in result.stderr
    assert "Traceback" not in result.stderr


def test_synthetic_demo_writes_its_figures(tmp_path):
    result = run("demo", "--synthetic", "--out", str(tmp_path / "out"))
    assert result.returncode == 0, result.stderr
    assert "the first occupied cell on the gaze is on the object: True" in result.stdout
    for name in ("fig3_worked_example.png", "fig5_gaze_on_object.png"):
        assert (tmp_path / "out" / name).stat().st_size > 10_000


def test_demo_names_what_each_gaze_lands_on(tmp_path):
    pytest.importorskip("skimage")
    pytest.importorskip("plotly")
    result = run("demo", "--out", str(tmp_path / "out"))
    assert result.returncode == 0, result.stderr
    assert "343,274 pixels with depth, 27,226 without (skipped)" in result.stdout
    for what, named in (("at the motorcycle", "motorcycle"), ("at the bench", "bench"),
                        ("at the shelves", "shelves"), ("at the floor", "no object")):
        assert re.search(rf"{what} +-?\d+ +-?\d+  {named} ", result.stdout), result.stdout
    assert (tmp_path / "out" / "motorcycle_gaze.png").stat().st_size > 10_000
    assert (tmp_path / "out" / "view.html").stat().st_size > 1_000_000


@pytest.fixture(scope="module")
def motorcycle_files(tmp_path_factory):
    """The Motorcycle frame as a user's files: depth (.npy, mm PNG, PFM), labels, names."""
    pytest.importorskip("skimage")
    from logsph_trace import datasets

    frame = datasets.motorcycle()
    folder = tmp_path_factory.mktemp("motorcycle")
    np.save(folder / "depth.npy", frame.depth)
    np.save(folder / "labels.npy", frame.labels)
    (folder / "names.json").write_text(json.dumps({str(k): v for k, v in frame.names.items()}))
    from PIL import Image

    millimetres = np.where(frame.valid, np.round(frame.depth * 1000), 0).astype(np.uint16)
    Image.fromarray(millimetres).save(folder / "depth.png")
    Image.fromarray(frame.labels.astype(np.uint16)).save(folder / "labels.png")
    with open(folder / "depth.pfm", "wb") as stream:
        stream.write(f"Pf\n{frame.depth.shape[1]} {frame.depth.shape[0]}\n-1.0\n".encode())
        stream.write(frame.depth[::-1].astype("<f4").tobytes())
    fx, fy, cx, cy = (frame.intrinsics[0, 0], frame.intrinsics[1, 1], frame.intrinsics[0, 2],
                      frame.intrinsics[1, 2])
    return folder, [str(v) for v in (fx, fy, cx, cy)]


def _look(folder, intrinsics, depth="depth.npy", *extra):
    return run("look", str(folder / depth), "--intrinsics", *intrinsics,
               "--eyes", "0.2", "-0.75", "3.0", *extra)


def test_look_names_the_motorcycle_first(motorcycle_files):
    folder, intrinsics = motorcycle_files
    names = ["--labels", str(folder / "labels.npy"), "--names", str(folder / "names.json")]
    result = _look(folder, intrinsics, "depth.npy", *names, "--pitch-yaw", "-52", "5")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0].split()[:3] == ["rank", "object", "name"]
    assert lines[1].split()[:3] == ["1", "1", "motorcycle"], result.stdout
    listed = json.loads(_look(folder, intrinsics, "depth.npy", *names, "--pitch-yaw", "-52", "5",
                              "--json").stdout)
    assert listed[0]["object"] == 1 and listed[0]["name"] == "motorcycle"
    assert set(listed[0]) == {"object", "name", "probability", "point", "distance"}
    assert listed[0]["probability"] > 0.99 and 0.2 < listed[0]["distance"] < 1.5
    point = np.array(listed[0]["point"])  # in the camera's frame: below the eyes, nearer
    assert point[1] > -0.75 and point[2] < 3.0
    probabilities = [entry["probability"] for entry in listed]
    assert probabilities == sorted(probabilities, reverse=True)


def test_look_reads_a_millimetre_png_and_a_pfm(motorcycle_files, tmp_path):
    folder, intrinsics = motorcycle_files
    names = ["--labels", str(folder / "labels.png"), "--names", str(folder / "names.json")]
    png = _look(folder, intrinsics, "depth.png", *names, "--depth-scale", "0.001",
                "--pitch-yaw", "-52", "5", "--json", "--html", str(tmp_path / "view.html"))
    assert png.returncode == 0, png.stderr
    assert json.loads(png.stdout)[0]["name"] == "motorcycle" and "warning" not in png.stderr
    assert (tmp_path / "view.html").stat().st_size > 1_000_000
    pfm = _look(folder, intrinsics, "depth.pfm", *names, "--gaze", "0", "0.8", "-0.6", "--json")
    assert pfm.returncode == 0, pfm.stderr
    assert json.loads(pfm.stdout)[0]["name"] == "motorcycle"
    # Without --depth-scale the millimetres are read as metres: a warning, then no object.
    wrong = _look(folder, intrinsics, "depth.png", *names, "--pitch-yaw", "-52", "5")
    assert "logsph-trace: warning: " in wrong.stderr and "depth_scale=0.001" in wrong.stderr


def test_look_finds_objects_without_labels(motorcycle_files):
    folder, intrinsics = motorcycle_files
    result = _look(folder, intrinsics, "depth.npy", "--pitch-yaw", "-52", "5", "--json")
    assert result.returncode == 0, result.stderr
    listed = json.loads(result.stdout)
    assert listed and listed[0]["object"] > 0 and "name" not in listed[0]


@pytest.mark.parametrize("args, message", [
    (["--names", "names.json"], "--names names the labels of --labels"),
    (["--labels", "missing.npy"], "no such labels file"),
    (["--half-angle", "95"], "--half-angle must be in [0, 90) degrees"),
    (["--depth-scale", "-1"], "depth_scale must be positive"),
    (["--grid", "0.3,8,64"], "--grid takes"),
])
def test_look_reports_bad_input_in_one_line(motorcycle_files, args, message):
    folder, intrinsics = motorcycle_files
    args = [str(folder / a) if a.endswith((".json", ".npy")) else a for a in args]
    result = _look(folder, intrinsics, "depth.npy", "--pitch-yaw", "-52", "5", *args)
    assert result.returncode == 2, result.stdout
    assert message in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert "Traceback" not in result.stderr


def test_look_needs_a_depth_file_it_can_read(tmp_path):
    (tmp_path / "depth.txt").write_text("1 2 3")
    for depth, message in (("depth.txt", "must be a .npy, .png or .pfm file"),
                           ("missing.npy", "no such depth file")):
        result = run("look", str(tmp_path / depth), "--intrinsics", "500", "500", "320", "240",
                     "--eyes", "0", "0", "1", "--gaze", "0", "0", "1")
        assert result.returncode == 2 and message in result.stderr, result.stderr
    no_gaze = run("look", str(tmp_path / "depth.txt"), "--intrinsics", "500", "500", "320", "240",
                  "--eyes", "0", "0", "1")
    assert no_gaze.returncode == 2 and "one of the arguments --pitch-yaw --gaze" in no_gaze.stderr


def test_warmup_compiles_and_says_so():
    result = run("warmup")
    assert result.returncode == 0, result.stderr
    assert re.match(r"logsph_trace: every CPU kernel ready in \d+\.\d s, cached", result.stdout)


def test_out_with_one_ray_is_an_error(tmp_path):
    result = run("trace", "--origin", "0", "20", "20", "--direction", "-0.3", "-0.01", "0",
                 "--out", str(tmp_path / "t.npz"))
    assert result.returncode == 2 and "--out writes a batch's traces" in result.stderr
    assert not (tmp_path / "t.npz").exists()


def test_bench_quick_writes_the_timing_study(tmp_path):
    result = run("bench", "--quick", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "fig4.png").exists() and (tmp_path / "fig4.json").exists()


def test_bench_runs_from_any_directory_without_importing_from_it(tmp_path):
    # A bench/ folder in the working directory must not be picked up.
    (tmp_path / "bench").mkdir()
    (tmp_path / "bench" / "__init__.py").write_text("raise SystemExit('imported from cwd')\n")
    result = run("bench", "--quick", "--out", str(tmp_path / "out"), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "out" / "fig4.json").exists()


def test_version_is_the_installed_metadata():
    from importlib.metadata import version

    assert lt.__version__ == version("logsph_trace")


def test_a_reader_that_stops_early_gets_no_traceback():
    command = _entry_point()
    process = subprocess.Popen(
        # A 3-degree cone's cells as JSON: ~2 MB, far past a pipe's buffer.
        [command, "trace", "--grid", "0.3,10,64,360,180", "--origin", "0.4", "1.6", "1.5",
         "--direction", "-0.2", "-0.5", "-1", "--cone", "3", "--format", "json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=REPO,
    )
    process.stdout.readline()  # like `| head -1`
    process.stdout.close()
    _, stderr = process.communicate(timeout=300)
    assert b"Traceback" not in stderr


def test_batches_are_traced_chunk_by_chunk(tmp_path, monkeypatch):
    from logsph_trace import cli

    monkeypatch.setattr(cli, "CHUNK_RAYS", 64)  # 500 rays: eight chunks, the last one short
    rng = np.random.default_rng(72)
    rays = np.hstack([rng.uniform(-90, 90, (500, 3)), rng.normal(size=(500, 3))])
    np.save(tmp_path / "rays.npy", rays)
    grid = lt.Grid.from_increments(10.0, 80.0, 10, d_theta=10.0, d_phi=10.0)
    count, segments, _ = cli._trace_batch(grid, cli._load_rays(tmp_path / "rays.npy"),
                                          tmp_path / "out.npz", progress=False)
    saved = np.load(tmp_path / "out.npz")
    want = lt.trace_many(grid, rays)
    assert count == 500 and segments == want.cells.shape[0]
    for name in ("offsets", "cells", "t_enter", "t_exit"):
        np.testing.assert_array_equal(saved[name], getattr(want, name))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.npz", "rays.npy"]  # no scratch left


# ---- the error contract ------------------------------------------------------------

RAY = ["--origin", "0", "20", "20", "--direction", "-0.3", "-0.01", "0"]


def _rays_file(tmp_path, n=300, bad_row=None):
    rng = np.random.default_rng(73)
    rays = np.hstack([rng.uniform(-90, 90, (n, 3)), rng.normal(size=(n, 3))])
    if bad_row is not None:
        rays[bad_row, 0] = np.nan
    path = tmp_path / "rays.npy"
    np.save(path, rays)
    return path, rays


@pytest.mark.parametrize("args, message", [
    (["--grid", "0.3,10,64,10000000000,180"], "not enough memory: n_theta"),
    (["--out", "no/such/dir/t.npz"], "--out: no such directory: no/such/dir"),
])
def test_os_and_memory_errors_are_one_line_exit_2(tmp_path, args, message):
    path, _ = _rays_file(tmp_path)
    result = run("trace", "--rays", str(path), "--out", str(tmp_path / "t.npz"), *args,
                 cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_an_unwritable_output_is_one_line_exit_2(tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root may write into a read-only directory")
    path, _ = _rays_file(tmp_path)
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        result = run("trace", "--rays", str(path), "--out", str(locked / "t.npz"))
    finally:
        locked.chmod(0o700)
    assert result.returncode == 2 and "Traceback" not in result.stderr


def test_a_bad_row_is_numbered_in_the_file(tmp_path, monkeypatch):
    from logsph_trace import cli

    monkeypatch.setattr(cli, "CHUNK_RAYS", 64)
    path, _ = _rays_file(tmp_path, bad_row=150)
    grid = lt.Grid(0.3, 10, 8, 8, 8)
    with pytest.raises(cli.CliError, match=r"origins must be finite; row 150 "):
        cli._trace_batch(grid, cli._load_rays(path), tmp_path / "t.npz", progress=False)


def test_out_names_the_file_written_and_writes_it_atomically(tmp_path):
    path, rays = _rays_file(tmp_path)
    (tmp_path / "t.csv.npz").write_bytes(b"old")
    result = run("trace", "--rays", str(path), "--out", str(tmp_path / "t.csv"))
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().endswith(f"-> {tmp_path / 't.csv.npz'}")
    assert np.load(tmp_path / "t.csv.npz")["offsets"].shape == (rays.shape[0] + 1,)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rays.npy", "t.csv.npz"]


def test_an_interrupted_batch_keeps_the_old_output(tmp_path, monkeypatch, capsys):
    from logsph_trace import cli

    path, _ = _rays_file(tmp_path)
    out = tmp_path / "t.npz"
    out.write_bytes(b"old")

    def interrupted(stream, array, **options):  # midway through the first array
        stream.write(b"partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(np.lib.format, "write_array", interrupted)
    status = cli.main(["trace", "--rays", str(path), "--out", str(out), "--quiet"])
    assert status == 130
    assert "interrupted" in capsys.readouterr().err
    assert out.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rays.npy", "t.npz"]


def test_cone_0_traces_the_one_ray():
    cone = run("trace", *RAY, "--cone", "0", "--format", "json")
    ray = run("trace", *RAY, "--format", "json")
    assert cone.returncode == 0, cone.stderr
    assert [[r["i"], r["j"], r["k"]] for r in json.loads(cone.stdout)] == \
        [[r["i"], r["j"], r["k"]] for r in json.loads(ray.stdout)]


def test_a_wide_cone_in_degrees_does_not_warn_about_radians():
    result = run("trace", *RAY, "--cone", "40", "--format", "json")
    assert result.returncode == 0 and "Warning" not in result.stderr


def test_grid_options_share_one_default_spacing():
    by_grid = run("trace", "--grid", "10,80,10,36,18", *RAY, "--format", "json")
    by_options = run("trace", "--rho", "10", "80", "--cells", "10", "36", "18", *RAY,
                     "--format", "json")
    assert by_grid.returncode == 0 and json.loads(by_grid.stdout) == json.loads(by_options.stdout)


def test_a_csv_header_row_is_accepted(tmp_path):
    _, rays = _rays_file(tmp_path)
    path = tmp_path / "rays.csv"
    np.savetxt(path, rays, delimiter=",", fmt="%.17g", header="ox,oy,oz,dx,dy,dz", comments="")
    result = run("trace", "--rays", str(path), "--out", str(tmp_path / "t.npz"), "--spacing",
                 "paper")
    assert result.returncode == 0, result.stderr
    grid = lt.Grid.from_increments(10.0, 80.0, 10, d_theta=10.0, d_phi=10.0)
    saved = np.load(tmp_path / "t.npz")
    np.testing.assert_array_equal(saved["offsets"], lt.trace_many(grid, rays).offsets)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a pty, as Linux makes one")
def test_the_progress_bar_shows_in_a_terminal_of_unknown_size(tmp_path):
    """A fresh pty reports a 0 x 0 screen, on which tqdm alone would hide its bar."""
    import pty

    path, _ = _rays_file(tmp_path)
    main, terminal = pty.openpty()
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    with subprocess.Popen([_entry_point(), "trace", "--rays", str(path), "--out",
                           str(tmp_path / "t.npz")], stdin=terminal, stdout=terminal,
                          stderr=terminal, cwd=REPO, env=env) as process:
        os.close(terminal)
        shown = b""
        while True:
            try:
                chunk = os.read(main, 4096)
            except OSError:  # EIO: the child closed its side
                break
            if not chunk:
                break
            shown += chunk
    os.close(main)
    # Colour resets (tqdm 4.70 writes one as it closes) are no frames of their own.
    text = re.sub(r"\x1b\[[0-9;]*m", "", shown.decode())
    frames = [f for f in text.replace("\n", "\r").split("\r") if f.strip()]
    assert process.returncode == 0, shown
    assert any(re.search(r"^100%.*\b300/300 .*ray/s", frame) for frame in frames), frames
    assert frames[-1].startswith("300 rays, ")


def test_no_progress_frames_in_a_log(tmp_path):
    path, _ = _rays_file(tmp_path)
    result = run("trace", "--rays", str(path), "--out", str(tmp_path / "t.npz"))
    assert result.returncode == 0 and "\r" not in result.stderr


def test_a_miss_says_0_cells():
    result = run("trace", "--origin", "0", "500", "0", "--direction", "0", "1", "0")
    assert result.returncode == 0 and result.stdout.startswith("0 cells")


def test_angle_ranges_that_look_like_radians_warn():
    result = run("trace", *RAY, "--theta-range", "-3.14", "3.14")
    assert "--theta-range -3.14 3.14 is in degrees: a 6.28-degree range" in result.stderr


def test_the_first_run_says_kernels_are_compiling(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"), MPLBACKEND="Agg")
    result = subprocess.run([_entry_point(), "trace", *RAY], capture_output=True, text=True,
                            cwd=REPO, env=env, timeout=600)
    assert result.returncode == 0, result.stderr
    assert result.stderr.count("compiling Numba kernels") == 1  # one line, however many compile
    again = subprocess.run([_entry_point(), "trace", *RAY], capture_output=True, text=True,
                           cwd=REPO, env=env, timeout=600)
    assert "compiling" not in again.stderr
