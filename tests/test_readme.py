"""The README's code blocks run as written, each in a fresh process; the docs link only inward.

The blocks run in order in one temporary folder, so a block may read a file
an earlier one wrote (as a user following the page would). The set-up
commands create virtual environments and install the package: CI's
``.ci/run`` runs each of them exactly as written, and this test checks that
it does.
"""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
BLOCK = re.compile(r"^```(python|bash)\n(.*?)^```", re.S | re.M)


def _blocks():
    return BLOCK.findall(README.read_text())


def test_the_readme_is_a_front_page():
    lines = README.read_text().splitlines()
    assert len(lines) <= 250, f"README.md has {len(lines)} lines: the docs site holds the rest"
    kinds = [kind for kind, _ in _blocks()]
    assert kinds.count("python") >= 3 and kinds.count("bash") >= 3


def test_every_set_up_command_is_what_ci_runs():
    ci = (ROOT / ".ci" / "run").read_text()
    set_up = [code.strip() for kind, code in _blocks()
              if kind == "bash" and code.startswith("python3 -m venv")]
    assert len(set_up) == 3  # the demo, the tests, the docs
    for command in set_up:
        assert command in ci.splitlines(), f".ci/run does not run {command!r} as written"


def test_every_other_block_runs_in_a_fresh_process(tmp_path):
    pytest.importorskip("skimage")
    pytest.importorskip("plotly")
    env = dict(os.environ, MPLBACKEND="Agg",
               PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    outputs = []
    for kind, code in _blocks():
        if kind == "bash" and code.startswith("python3 -m venv"):
            continue
        command = [sys.executable, "-c", code] if kind == "python" else ["bash", "-e", "-c", code]
        result = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True,
                                timeout=600)
        assert result.returncode == 0, f"{kind} block failed:\n{code}\n{result.stderr}"
        outputs.append(result.stdout)
    text = "\n".join(outputs)
    assert re.search(r"^motorcycle: p = 1\.00, 0\.\d\d m from the eyes$", text, re.M), text
    assert re.search(r"^ +1 +1 motorcycle ", text, re.M), text  # logsph-trace look
    assert (tmp_path / "view.html").stat().st_size > 1_000_000


def _pages():
    return [README, *sorted((ROOT / "docs").rglob("*.md"))]


def test_docs_link_only_to_files_in_the_repository():
    """Whoever clones the project has what the README and docs/ point to."""
    for page in _pages():
        text = page.read_text()
        assert "shared/" not in text, f"{page.name} points outside the repository"
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
            if "://" in target or target.startswith("mailto:"):
                continue
            assert (page.parent / target).exists(), f"{page.name} links to a missing {target}"
        for path in re.findall(r"`((?:bench|docs|tests|notebooks|logsph_trace)/[\w./-]+)`", text):
            assert (ROOT / path).exists(), f"{page.name} names a missing {path}"


def test_the_how_to_examples_run_in_a_fresh_process(tmp_path):
    """Each how-to page's Python blocks run in order, as a reader would paste them
    (but the GPU page's, which need a GPU)."""
    env = dict(os.environ, MPLBACKEND="Agg")
    for page in sorted((ROOT / "docs" / "how-to").glob("*.md")):
        if page.name == "gpu.md":
            continue
        blocks = [code for kind, code in BLOCK.findall(page.read_text()) if kind == "python"]
        if not blocks:
            continue
        result = subprocess.run([sys.executable, "-c", "\n".join(blocks)], cwd=tmp_path,
                                env=env, capture_output=True, text=True, timeout=600)
        assert result.returncode == 0, f"{page.name}:\n{result.stderr}"
        if page.name == "moving-robot.md":
            assert result.stdout.strip().splitlines()[-1] == "object", result.stdout
