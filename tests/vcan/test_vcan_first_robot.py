"""docs/first-robot.md, run: every ``$`` command of the page in page order, in a checkout's
folder (the project's eds/ as the drive files) on vcan0 (the page's can0), each one's
output compared with what the page shows (tests/fixtures/doc_page.py: ``...`` stands for
lines or text cut), and the config init-config wrote with the page's excerpt of it.

The page's ``&`` command (the bench's drives) and ``run`` do not end by themselves: they run
in the background, ``run`` until its first lines are the page's; they are stopped with
SIGINT at the end (a Ctrl-C), run first, and must exit 0. Before each ``status`` the test
waits until the manager has settled (bring-up finished, the drives of a switch enabled),
as a person reads the status after a look at the robot."""
from __future__ import annotations

import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

from fixtures.budgets import GUEST_STALL, within
from fixtures.doc_page import blocks, excerpt, matches, steps

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "first-robot.md"
BIN = Path(sys.executable).parent
#: a CLI command in the guest: its start alone took 8.5 s once beside a manager (see
#: test_e2e_manager.cli)
COMMAND = 180.0
#: bring-up and a switch's enabling, at 25 Hz in the guest
SETTLE = within(20.0, GUEST_STALL)


def bench(text: str) -> str:
    """The page's can0 as this bench's vcan0."""
    return re.sub(r"\bcan0\b", "vcan0", text)


def _env() -> dict[str, str]:
    return {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}


def _status(cwd: Path) -> dict | None:
    done = subprocess.run([str(BIN / "rocoma-can"), "status", "--json", "--channel", "vcan0"],
                          cwd=cwd, env=_env(), capture_output=True, text=True,
                          timeout=COMMAND)
    return json.loads(done.stdout) if done.returncode == 0 else None


def _settle(cwd: Path) -> None:
    """Until bring-up has finished and, in OK, every drive is enabled."""
    deadline = time.monotonic() + SETTLE
    report = None
    while time.monotonic() < deadline:
        report = _status(cwd)
        if report and report["startup_finished"] and all(
                d["phase"] == "READY" and (d["enabled"] or report["state"] != "OK")
                for d in report["drives"]):
            return
        time.sleep(0.5)
    raise AssertionError(f"the manager did not settle within {SETTLE} s: {report}")


def test_every_command_of_the_page_prints_what_the_page_shows(tmp_path):
    (tmp_path / "eds").symlink_to(ROOT / "eds")
    session = steps(PAGE)
    background: list[tuple[str, subprocess.Popen, Path]] = []
    try:
        for k, step in enumerate(session):
            if not step.command.startswith("rocoma-can "):  # a shell's (the bench's margins)
                done = subprocess.run(["bash", "-c", step.command], cwd=tmp_path,
                                      env=_env(), capture_output=True, text=True,
                                      timeout=COMMAND)
                assert (done.returncode, done.stdout + done.stderr) == (0, ""), step.command
                continue
            argv = shlex.split(bench(step.command))
            shown = [bench(line) for line in step.shown]
            if step.background or argv[1] == "run":
                log = tmp_path / f"{k}-{argv[1]}.log"
                with log.open("w") as out:
                    background.append((argv[1], subprocess.Popen(
                        argv, cwd=tmp_path, env=_env(), stdout=out,
                        stderr=subprocess.STDOUT, text=True), log))
                if shown:
                    deadline = time.monotonic() + COMMAND
                    while not matches(shown, log.read_text().splitlines()):
                        assert background[-1][1].poll() is None and \
                            time.monotonic() < deadline, f"{step.command}: {log.read_text()}"
                        time.sleep(0.2)
                continue
            if argv[1] == "status":
                _settle(tmp_path)
            done = subprocess.run(argv, cwd=tmp_path, env=_env(), capture_output=True,
                                  text=True, timeout=COMMAND)
            printed = (done.stdout + done.stderr).splitlines()
            assert done.returncode == 0, (step.command, done.stdout, done.stderr)
            assert matches(shown, printed), \
                "\n".join([f"$ {step.command}", "-- the page shows:", *shown,
                           "-- it printed:", *printed])
            if argv[1] == "init-config":
                (yaml_block,) = [b for b in blocks(PAGE) if b.language == "yaml"]
                written = (tmp_path / "robot.yaml").read_text()
                assert excerpt([bench(line) for line in yaml_block.lines], written), written
    finally:
        for name, process, log in reversed(background):  # run first, then the drives
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
            try:
                process.wait(COMMAND)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(GUEST_STALL)
            print(f"--- {name} (exit {process.returncode}):\n{log.read_text()[-4000:]}")
    assert [(name, p.returncode) for name, p, _ in background] == [("sim", 0), ("run", 0)]
