"""The README's controller example runs as written (docs that cannot rot silently)."""
from __future__ import annotations

import re
from pathlib import Path

README = Path(__file__).resolve().parent.parent / "README.md"


def test_readme_controller_example_runs():
    text = README.read_text()
    section = text[text.index("## Writing a controller"):]
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)[:2]
    assert len(blocks) == 2
    namespace: dict = {}
    exec(compile(blocks[0] + blocks[1], str(README), "exec"), namespace)
    assert namespace["mgr"].state.name == "FAILPROOF"  # after the with-block: shut down
    assert namespace["command"].mode.tolist() == [0] * 6  # torque-off written at shutdown
