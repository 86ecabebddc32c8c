"""The installed ``logsph-trace`` entry point, run as a user would, in a subprocess."""

import json
import os
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
    args = ["trace", "--origin", "0", "20", "20", "--direction", "-0.3", "-0.01", "0"]
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
    result = run("trace", "--rays", str(path), "--out", str(out), "--quiet")
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
         "half_angle must be in [0, pi/2)"),
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


def test_demo_writes_its_figures(tmp_path):
    result = run("demo", "--out", str(tmp_path / "out"))
    assert result.returncode == 0, result.stderr
    assert "the first occupied cell on the gaze is on the object: True" in result.stdout
    for name in ("fig3_worked_example.png", "fig5_gaze_on_object.png"):
        assert (tmp_path / "out" / name).stat().st_size > 10_000


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
