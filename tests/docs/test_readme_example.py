"""README.md, docs/controllers.md: the controller example runs as written, in the README and on the
docs page it comes from (docs/controllers.md): docs that cannot rot silently."""
from __future__ import annotations

import re

import pytest
from fixtures.paths import ROOT


@pytest.mark.parametrize("page", ["README.md", "docs/controllers.md"])
def test_controller_example_runs(page):
    text = (ROOT / page).read_text()
    section = text[re.search(r"^#+ Writing a controller$", text, re.M).start():]
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)[:2]
    assert len(blocks) == 2
    namespace: dict = {}
    exec(compile(blocks[0] + blocks[1], str(ROOT / page), "exec"), namespace)
    assert namespace["mgr"].state.name == "FAILPROOF"  # after the with-block: shut down
    assert namespace["command"].mode.tolist() == [0] * 6  # torque-off written at shutdown
