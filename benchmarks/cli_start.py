"""How long a ``rocoma-can`` command takes to start, and how much it imports.

    .venv/bin/python benchmarks/cli_start.py [--repeat 5] [--socketcan]

Each command runs as a fresh process (``python -X importtime -m rocoma_can ...``), like an
operator's shell or a PLC script starts it: wall time from spawn to exit, modules imported,
and whether numpy was. A bus verb only needs python-can and canopen; every start competes
with the machine's own control loop for the CPU, which is why the verbs import lazily.

``status`` is a real SDO exchange with a manager node served by this process: over
SocketCAN vcan0 with ``--socketcan`` (run it under tools/vcan-run on a machine without
vcan); without it, python-can's virtual bus cannot reach another process, so the row is a
start, one SDO request and the 0.2 s timeout with nobody answering (exit code 3).
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time

from _report import report, stats

COMMANDS = {
    "python -c pass": ["-c", "pass"],
    "import rocoma_can": ["-c", "import rocoma_can"],
    "rocoma-can --help": ["-m", "rocoma_can", "--help"],
    "rocoma-can status --help": ["-m", "rocoma_can", "status", "--help"],
}


def run_once(args: list[str]) -> tuple[float, int, bool, int]:
    """(seconds, modules imported, numpy imported, exit code) of one fresh process."""
    started = time.perf_counter()
    proc = subprocess.run([sys.executable, "-X", "importtime", *args], capture_output=True,
                          text=True, timeout=120)
    seconds = time.perf_counter() - started
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("import time:")]
    modules = len(lines) - 1  # the header line
    numpy = any(ln.rstrip().endswith("| numpy") for ln in lines)
    return seconds, modules, numpy, proc.returncode


def served_manager(interface: str, channel: str):
    """A manager with its CANopen node (id 100) on ``channel``, for a real status call."""
    from rocoma_can import ControllerManager
    from rocoma_can.controllers.torque_off import TorqueOff
    from rocoma_can.drivers.link.bus import open_bus
    from rocoma_can.node.server import ManagerNode
    manager = ControllerManager(TorqueOff(), 0.01)
    bus = open_bus(interface, channel)  # as rocoma-can run opens the node's bus
    node = ManagerNode(manager, 100, bus).start()

    def close() -> None:
        node.close()
        bus.shutdown()
        manager.shutdown()
    return close


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--socketcan", action="store_true",
                        help="status against a manager node on vcan0 (needs SocketCAN)")
    parser.add_argument("--quick", action="store_true", help="--repeat 1")
    args = parser.parse_args()
    repeat = 1 if args.quick else args.repeat

    interface, channel = ("socketcan", "vcan0") if args.socketcan else ("virtual", "bench")
    commands = dict(COMMANDS)
    commands["rocoma-can status" + ("" if args.socketcan else " (no answer)")] = [
        "-m", "rocoma_can", "status", "--interface", interface, "--channel", channel,
        "--timeout", "2.0" if args.socketcan else "0.2"]
    close = served_manager(interface, channel) if args.socketcan else None
    rows, results = [], {}
    try:
        for name, cmd in commands.items():
            runs = [run_once(cmd) for _ in range(repeat)]
            s = stats([r[0] for r in runs])
            results[name] = {"seconds": s, "modules": runs[-1][1], "numpy": runs[-1][2],
                             "exit_code": runs[-1][3]}
            rows.append([name, s["median"] * 1e3, s["max"] * 1e3, runs[-1][1],
                         "yes" if runs[-1][2] else "no", runs[-1][3]])
    finally:
        if close is not None:
            close()
    report("cli_start", f"CLI start, fresh process ({repeat} runs each)",
           ["command", "median ms", "max ms", "modules", "numpy", "exit"], rows, args=args,
           results=results)


if __name__ == "__main__":
    main()
