"""The README's Python example runs as it is and does what its comments say."""

import re

import numpy as np
import pytest

import fluid_surfels as fs
from conftest import ROOT


@pytest.mark.repository
def test_the_readme_example_runs(tmp_path, monkeypatch, capsys):
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## From Python"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    monkeypatch.chdir(tmp_path)
    scope = {}
    exec(compile(code, "README.md", "exec"), scope)
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 15 and lines[-1].startswith("14 ")
    assert scope["image"].shape[2] == 4 and scope["image"].dtype == np.uint8
    written = fs.read(tmp_path / "surfels.ply")
    np.testing.assert_array_equal(written["positions"], scope["frame"].surfels.positions)


@pytest.mark.repository
def test_the_wheels_readme_example_runs(monkeypatch, tmp_path):
    """python/README.md (the wheel's description): its first example runs as it is."""
    text = (ROOT / "python" / "README.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    monkeypatch.chdir(tmp_path)
    scope = {}
    exec(compile(code, "python/README.md", "exec"), scope)
    assert scope["image"].shape[2] == 4 and scope["image"].dtype == np.uint8
    assert len(scope["frame"].surfels) > 0
