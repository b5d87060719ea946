"""Plain-Python use without Hydra, exactly as the README shows it."""

from __future__ import annotations

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_example_runs(tmp_path, monkeypatch):
    block = re.search(r"<!-- api-example -->\s*```python\n(.*?)```", README.read_text(), re.S)
    assert block, "README must contain the marked Python API example"
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(block.group(1), "README-example", "exec"), namespace)
    result = namespace["result"]
    assert result.frames >= 300 and result.eval_episodes == 5
    assert (tmp_path / "runs" / "api-demo" / "summary.json").exists()
