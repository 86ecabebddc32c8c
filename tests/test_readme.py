"""The README's example runs as written."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_example_runs(capsys):
    text = README.read_text()
    block = re.search(r"## Example\n\n```python\n(.*?)```", text, re.S).group(1)
    exec(compile(block, "README.md example", "exec"), {})
    out = capsys.readouterr().out
    assert "cells; the first five:" in out and "cell (" in out
