"""The README's examples run as written (later ones reuse the first one's names)."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_examples_run(capsys):
    text = README.read_text()
    example = re.search(r"## Example\n\n```python\n(.*?)```", text, re.S).group(1)
    cone = re.search(r"## Gaze cones\n\n.*?```python\n(.*?)```", text, re.S).group(1)
    occupancy = re.search(r"## Occupancy and what a person looks at\n\n```python\n(.*?)```",
                          text, re.S).group(1)
    names = {}
    exec(compile(example, "README.md example", "exec"), names)
    exec(compile(cone, "README.md gaze cone example", "exec"), names)
    exec(compile(occupancy, "README.md occupancy example", "exec"), names)
    out = capsys.readouterr().out
    assert "cells; the first five:" in out and "cell (" in out
    assert abs(names["cone"].weights.sum() - 1.0) < 1e-12
    assert len(names["seen"]) > 0 and len(names["looked_at"]) > 0


def test_docs_link_only_to_files_in_the_repository():
    """Whoever clones the project has what the README and docs/ point to."""
    root = README.parent
    for page in [README, *sorted((root / "docs").glob("*.md"))]:
        text = page.read_text()
        assert "shared/" not in text, f"{page.name} points outside the repository"
        for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text):
            if "://" in target:
                continue
            assert (page.parent / target).exists(), f"{page.name} links to a missing {target}"
        for path in re.findall(r"`((?:bench|docs|tests|notebooks|logsph_trace)/[\w./-]+)`", text):
            assert (root / path).exists(), f"{page.name} names a missing {path}"
