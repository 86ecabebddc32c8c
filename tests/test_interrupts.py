"""Ctrl-C at random moments: every public call raises ``KeyboardInterrupt``, and
the objects it was working on work afterwards; the command line exits 130 with
one line.

A child process loops over the calls that run parallel kernels (batches,
cones, both integration paths, a fixation probability) while the test sends
it SIGINT at random intervals. After each interrupt the child checks that a
trace and the map it was updating still give what an untouched copy gives.
"""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]

CHILD = r"""
import select, sys
import numpy as np
import logsph_trace as lt

grid = lt.Grid(0.3, 10.0, 32, 64, 32)
rng = np.random.default_rng(0)
rays = rng.normal(size=(300_000, 6))
points = rng.normal(size=(150_000, 3)) * 3.0
sensor = [0.1, 0.0, 0.05]
small = rays[:3000]
want = lt.trace_many(grid, small)
bvm = lt.OccupancyGrid(grid)
bvm.integrate(points[:1000], sensor)
calls = [
    lambda: lt.trace_many(grid, rays),
    lambda: lt.trace_cones(grid, rays[:300, :3], rays[:300, 3:], 0.1),
    lambda: bvm.integrate(points, sensor),
    lambda: bvm.integrate(points, [0.0, 0.0, 0.0]),
    lambda: lt.fixation_probability(bvm, [0.1, 0.2, 0.3], [1.0, 0.2, 0.1], 0.1, n_rays=20_000),
]


def check():
    got = lt.trace_many(grid, small)
    assert np.array_equal(got.cells, want.cells) and np.array_equal(got.t_exit, want.t_exit)
    copy = lt.OccupancyGrid(grid)
    copy.log_odds = bvm.log_odds.copy()
    for scan in (bvm, copy):
        scan.integrate(points[:5000], sensor)
    assert np.array_equal(copy.log_odds, bvm.log_odds)


for call in calls:  # compiled before the signals come
    call()
state = {"interrupted": 0, "pending": False, "errors": []}


def run():
    while True:
        try:
            if state["pending"]:  # an interrupted check is checked again
                check()
                state["pending"] = False
            if select.select([sys.stdin], [], [], 0)[0]:
                return
            for call in calls:
                call()
        except KeyboardInterrupt:
            state["interrupted"] += 1
            state["pending"] = True
        except Exception as error:
            state["errors"].append(repr(error))
            state["pending"] = False


print("ready", flush=True)
while True:
    try:
        run()
        break
    except KeyboardInterrupt:  # one that came between the statements of run's loop
        state["interrupted"] += 1
        state["pending"] = True
interrupted, errors = state["interrupted"], state["errors"]
print("interrupted", interrupted, "errors", errors, flush=True)
"""


def _child_env():
    return dict(os.environ, PYTHONFAULTHANDLER="1", MPLBACKEND="Agg")


def test_ctrl_c_at_random_moments_raises_keyboard_interrupt_and_leaves_objects_working():
    child = subprocess.Popen([sys.executable, "-c", CHILD], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             cwd=REPO, env=_child_env())
    try:
        assert child.stdout.readline().strip() == "ready", child.stderr.read()
        rng = np.random.default_rng(52)
        for pause in rng.uniform(0.05, 0.5, 40):
            time.sleep(pause)
            child.send_signal(signal.SIGINT)
        time.sleep(0.5)
        out, err = child.communicate("stop\n", timeout=300)
    finally:
        child.kill()
    assert child.returncode == 0, err[-3000:]
    words = out.split()
    assert words[0] == "interrupted" and int(words[1]) >= 20, out
    assert out.strip().endswith("errors []"), out + err[-3000:]


def _entry_point():
    found = Path(sys.executable).parent / "logsph-trace"
    return str(found) if found.exists() else None


@pytest.mark.skipif(_entry_point() is None, reason="the logsph-trace entry point is not installed")
def test_the_command_line_interrupted_exits_130_with_one_line(tmp_path):
    rays = np.random.default_rng(1).normal(size=(1_000_000, 6))
    np.save(tmp_path / "rays.npy", rays)
    command = [_entry_point(), "trace", "--rays", str(tmp_path / "rays.npy"), "--out",
               str(tmp_path / "traces.npz")]
    # Once whole, so the kernels are compiled and the runs below start alike:
    # about a second to start, two or three to trace and write.
    assert subprocess.run(command, capture_output=True, env=_child_env()).returncode == 0
    (tmp_path / "traces.npz").unlink()
    interrupted = 0
    for delay in np.random.default_rng(130).uniform(0.0, 1.0, 5):
        child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                 text=True, env=_child_env())
        try:
            # The command has started its work once it makes its scratch folder
            # beside the output (before, Python is still importing).
            while child.poll() is None and len(list(tmp_path.iterdir())) < 2:
                time.sleep(0.005)
            time.sleep(delay)
            child.send_signal(signal.SIGINT)
            _, err = child.communicate(timeout=300)
        finally:
            child.kill()
        if child.returncode == 0:
            (tmp_path / "traces.npz").unlink()  # it finished before the signal came
            continue
        interrupted += 1
        assert child.returncode == 130, err
        assert err.strip().splitlines() == [
            "logsph-trace: interrupted; no partial output was written"], err
        assert not (tmp_path / "traces.npz").exists()
    assert interrupted >= 2
