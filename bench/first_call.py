"""The first answer: the README's main job in a fresh process, with an empty cache and a warm one.

    python -m bench.first_call              # 3 rounds
    python -m bench.first_call --rounds 5

The main job is the README's first Python block (the real depth frame, the
map, its objects, a gaze, the named object), run as written. Each round
starts a fresh Python with ``NUMBA_CACHE_DIR`` pointing at a new, empty
folder (cold: every kernel the job needs compiles and is cached there),
then another fresh Python on the same folder (warm: every kernel loads).
Wall time of the whole process, imports included; the package is this
tree's, first on the path, whatever is installed. Also counts the kernels
the cold run compiled, and the seconds each took (Numba's compile events,
outermost kernels only). Writes ``bench/results/first_call.json`` (and
``.md``).
"""

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.workload import write_results

ROOT = Path(__file__).resolve().parent.parent

# Runs the main job with Numba's compile events counted, outermost kernels only.
PROBE = """
import collections, json, sys, time
from numba.core import event
stack, seconds = [], collections.Counter()
class Kernels(event.Listener):
    def on_start(self, ev):
        stack.append((ev.data["dispatcher"].py_func.__qualname__, time.perf_counter()))
    def on_end(self, ev):
        name, start = stack.pop()
        if not stack:
            seconds[name] += time.perf_counter() - start
event.register("numba:compile", Kernels())
exec(compile(open(sys.argv[1]).read(), "main_job", "exec"))
print(json.dumps(dict(seconds)))
"""


def main_job():
    """Return the README's first Python block (the main job)."""
    return re.findall(r"^```python\n(.*?)^```", (ROOT / "README.md").read_text(),
                      re.S | re.M)[0]


def run(script, cache, probe):
    """Run ``script`` in a fresh Python with the cache in ``cache``; (seconds, kernels)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), LOGSPH_TRACE_COMPILE_NOTE="0")
    env.pop("LOGSPH_TRACE_CACHE", None)
    # This tree's package first, whatever is installed (as bench.ab runs each tree).
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + env.get("PYTHONPATH", "").split(os.pathsep))
    command = [sys.executable, "-c", PROBE, str(script)] if probe else [sys.executable, script]
    start = time.perf_counter()
    done = subprocess.run(command, env=env, cwd=ROOT, capture_output=True, text=True, check=True)
    seconds = time.perf_counter() - start
    return seconds, json.loads(done.stdout.splitlines()[-1]) if probe else None


def measure(rounds):
    """Time the main job cold and warm, ``rounds`` times each, alternated."""
    cold, warm, compiles = [], [], []
    with tempfile.TemporaryDirectory() as folder:
        script = Path(folder) / "main_job.py"
        script.write_text(main_job())
        for k in range(rounds):
            cache = Path(folder) / f"cache-{k}"
            seconds, _ = run(script, cache, probe=False)
            cold.append(seconds)
            warm.append(run(script, cache, probe=False)[0])
        # One more cold run, with the compile events counted (the listener costs a little).
        compiles = run(script, Path(folder) / "cache-probe", probe=True)[1]
    return {"rounds": rounds, "cold_s": cold, "warm_s": warm,
            "cold_median_s": statistics.median(cold), "warm_median_s": statistics.median(warm),
            "compiled_s": dict(sorted(compiles.items(), key=lambda kv: -kv[1]))}


def report(result):
    """Return the record's page."""
    lines = [
        f"The README's main job in a fresh process, {result['rounds']} rounds: "
        f"cold (empty cache) median **{result['cold_median_s']:.1f} s** "
        f"({', '.join(f'{s:.1f}' for s in result['cold_s'])}); "
        f"warm median **{result['warm_median_s']:.2f} s** "
        f"({', '.join(f'{s:.2f}' for s in result['warm_s'])}). Wall time, imports included.",
        "",
        "Kernels a cold run compiled (outermost calls; seconds, in one more cold run):",
        "",
        "| kernel | s |",
        "|---|---:|",
    ]
    lines += [f"| `{name}` | {seconds:.2f} |" for name, seconds in result["compiled_s"].items()]
    lines += ["", f"{len(result['compiled_s'])} kernels, "
              f"{sum(result['compiled_s'].values()):.1f} s compiling in all."]
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args(argv)
    result = measure(args.rounds)
    write_results("first_call", argv, report(result), result)


if __name__ == "__main__":
    main()
