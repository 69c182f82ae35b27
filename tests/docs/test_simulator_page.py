"""docs/simulator.md's command for a bench without SocketCAN on the host, run as the page
writes it: a simulator in the background of a ``bash -c``, a timed run beside it, under
tools/vcan-run. It returned only at the runner's timeout (1800 s): the simulator left in the
background kept the guest up. It must end with the run's status, the run having brought the
drives up, and stop its simulator itself (on a host with vcan nothing else would)."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from fixtures.paths import ROOT

PAGE = ROOT / "docs" / "simulator.md"
#: the page's run is 20 s; the guest's boot and each Python start in it cost seconds more
BUDGET = 600


def page_command() -> str:
    """The page's ``tools/vcan-run bash -c '...'`` block, as written."""
    blocks = re.findall(r"```bash\n(tools/vcan-run .*?)```", PAGE.read_text(), re.S)
    assert len(blocks) == 1, blocks
    return blocks[0]


def test_the_pages_bench_command_ends_with_the_runs_status(uml):  # noqa: F811
    env = dict(os.environ, **uml, ROCOMA_VCAN_TIMEOUT=str(BUDGET),
               PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    done = subprocess.run(["bash", "-c", page_command()], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=BUDGET + 60)
    out = done.stdout + done.stderr
    assert done.returncode == 0, out
    assert "bring-up finished in " in out and ": 3 drives ready (j1, j2, j3)" in out, out
    assert "stopped (duration reached); cycles " in out, out
    assert "ending what it left running" not in out, out  # the page stops its simulator


def test_the_examples_comment_shows_the_pages_command():
    example = (ROOT / "rocoma_can" / "examples" / "bench_uml.yaml").read_text()
    said = "\n".join(line.removeprefix("#").strip() for line in example.splitlines()
                     if line.startswith("#   ") or line.startswith("#     "))
    assert " ".join(said.split()) == " ".join(page_command().split())
