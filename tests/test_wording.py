"""The product speaks of the product: no words from the team's work log in what ships.

Code, tests, docs, notebooks and benchmark records state contracts, units,
frames and measurements. How they came about (machines used along the way,
periods of work, issue numbers) lives in git's history and CHANGELOG.md.
"""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SKIPPED_DIRS = {".git", ".venv", ".venv-min", ".venv-cuda", "site", "build", "__pycache__",
                ".pytest_cache", ".benchmarks", ".hypothesis", "logsph-trace-out", ".whl", ".cache"}
TEXT = {".py", ".md", ".ipynb", ".toml", ".txt", ".sh", ".yml", ".yaml", ".json", ".cfg", ""}
WORK_LOG = [
    (re.compile(r"\bVMs?\b"), "the machine the work ran on"),
    (re.compile(r"firecracker", re.I), "the sandbox"),
    (re.compile(r'(?<!scope=")\bsessions?\b', re.I), "a period of work"),
    (re.compile(r"\bissues? ?#? ?\d+", re.I), "an issue number"),
    (re.compile(r"\bissue\d+", re.I), "an issue number"),
    (re.compile(r"\b(earlier|previous|older|other) (machine|run|round|probe)s?\b", re.I),
     "an earlier period of work"),
    (re.compile(r"\b(this|last) round\b", re.I), "a round of work"),
    (re.compile(r"\bwork ?log\b", re.I), "the work log"),
    (re.compile(r"\blent to\b", re.I), "a machine lent for a while"),
]
# Dates belong to records (JSON, written by the benchmarks) and the changelog.
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")


def _files():
    for path in sorted(ROOT.rglob("*")):
        parts = set(path.relative_to(ROOT).parts)
        if parts & SKIPPED_DIRS or not path.is_file() or path.suffix not in TEXT:
            continue
        if path.name.endswith(".egg-info") or any(p.endswith(".egg-info") for p in parts):
            continue
        yield path


def test_no_work_log_words_in_the_product():
    found = []
    for path in _files():
        if path == Path(__file__):
            continue
        text = path.read_text(errors="replace")
        name = path.relative_to(ROOT).as_posix()
        for pattern, what in WORK_LOG:
            for match in pattern.finditer(text):
                line = text.count("\n", 0, match.start()) + 1
                found.append(f"{name}:{line}: {match.group(0)!r} ({what})")
        if name != "CHANGELOG.md" and not (name.startswith("bench/results/")
                                           and path.suffix == ".json"):
            for match in DATE.finditer(text):
                line = text.count("\n", 0, match.start()) + 1
                found.append(f"{name}:{line}: {match.group(0)!r} (a date outside a record)")
    assert not found, "\n".join(found[:60]) + f"\n({len(found)} in all)"


def test_the_benchmark_records_are_one_per_benchmark():
    """bench/results holds what the benchmark scripts write, and nothing else."""
    results = ROOT / "bench" / "results"
    scripts = {path.stem for path in (ROOT / "bench").glob("*.py")}
    records = {path.stem: path for path in results.iterdir()}
    strays = sorted(name for name in records if name not in scripts | {"traversal"})
    assert not strays, f"bench/results holds files no benchmark writes: {strays}"
    for path in results.glob("*.md"):
        assert path.read_text().startswith("`python -m bench."), \
            f"{path.name} does not start with the command that writes it"
