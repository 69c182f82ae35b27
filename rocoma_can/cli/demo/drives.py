"""The demo's simulated drives, in the loop's process (the default) or in one of their own.

In its own process (``SimProcess``) the simulator costs the control loop what real drives
would: the frames. The child (``python -m rocoma_can.cli.demo.drives``, started here) opens a
segment of drives per bus on its own in-process channels, joins the channels to the demo's
over a socket pair (drivers/link/inproc_link.py), and on its main thread reads the link and
steps the drives that got frames at once (drivers/sim/group.py's lockstep pass). The
operator's fault injections and the final check go over the child's stdin and stdout, one
JSON line each way, matched by id; the child ends on ``stop``, when its stdin closes or its
link ends (the demo ended or died), never on a signal meant for the demo.

In the loop's process (``InProcessSim``) the loop's thread steps the simulator after each
write (lockstep; group.py says why that beats a thread of its own in a shared interpreter).
Either way the demo sees one ``DemoSimulator``.

``--sim loop`` is the default: measured on 2 cores, 12 drives on 4 buses at 1 kHz, the
drives' process halved the loop's work per cycle (and, in the demo without recording, its
overruns), but it is a third busy process (~0.4 of a core): with recording on, the loop,
the writer and the drives on two cores overran 1-3x as often as with the lockstep
simulator (benchmarks/HISTORY.md). ``--sim process`` is for a host with a core for each.
"""
from __future__ import annotations

import itertools
import json
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import IO, TYPE_CHECKING, Any, Protocol

from ...errors import SimulatorFailed

if TYPE_CHECKING:
    from ...drivers.sim.group import SegmentGroup
    from ...drivers.sim.segment import SimulatedSegment
    from .config import Emulated

#: s the child may take to import, open its buses and power its drives on
START_TIMEOUT = 30.0
#: s a request to the child may take to be answered
REPLY_TIMEOUT = 5.0
#: s the child's link waits for frames before it looks for its end again
LINK_IDLE = 0.1
#: s the child has to end after ``stop`` before it is killed
STOP_TIMEOUT = 5.0

#: ``--sim`` choices: where the drives run
SIM_CHOICES = ("loop", "process")

#: (channel, node ids of the drives on it) per bus, in the buses' order
Buses = Sequence[tuple[str, Sequence[int]]]


class DemoSimulator(Protocol):
    """What the demo's operator and its end need from the simulated drives."""
    @property
    def node_ids(self) -> Sequence[int]:
        """Node ids of the drives on the first bus (the operator's faults go there)."""
        ...

    @property
    def where(self) -> str:
        """Where the drives run, for the demo to say."""
        ...

    def trip_fault(self, node: int) -> float:
        """Trip drive ``node``'s fault (first bus); the monotonic time it was tripped."""
        ...

    def check(self) -> None:
        """Raise when the simulation failed (a drive raised, the process died)."""
        ...

    def stop(self) -> None: ...


def check_choice(sim: str, interface: str) -> None:
    """ValueError for a ``--sim`` that is not one, or a process on an interface no link
    joins (python-can's ``virtual``)."""
    if sim not in SIM_CHOICES:
        raise ValueError(f"--sim must be one of {', '.join(SIM_CHOICES)}, got {sim!r}")
    if sim == "process" and interface != "inproc":
        raise ValueError(f"--sim process needs --interface inproc: the {interface} bus joins "
                         "no other process")


def open_segments(buses: Buses, interface: str, emulated: Emulated | None,
                  fd: bool) -> list[SimulatedSegment]:
    """One segment per bus, its drives emulating ``emulated``'s file (or the generic drive)."""
    from ...drivers.sim.segment import SimulatedSegment
    segments: list[SimulatedSegment] = []
    try:
        for channel, nodes in buses:
            extra: dict[str, Any] = dict(emulated.segment) if emulated else {}
            if emulated and emulated.axes > 1:
                extra["axes"] = {node: emulated.axes for node in nodes}
            segments.append(SimulatedSegment.open(channel, interface, list(nodes), fd=fd,
                                                  **extra))
    except BaseException:
        for segment in segments:
            segment.stop()
        raise
    return segments


class InProcessSim:
    """The drives in this process, stepped in lockstep by a caller's thread: the loop's
    (``on_cycle``), or the drives' own process's link reader (``main``)."""

    def __init__(self, buses: Buses, interface: str, emulated: Emulated | None,
                 fd: bool) -> None:
        from ...drivers.sim.group import SegmentGroup
        self.segments = open_segments(buses, interface, emulated, fd)
        self.node_ids = self.segments[0].node_ids
        self.where = "in this process, stepped by the loop after each write"
        self.pid: int | None = None  # (no process of their own)
        self.group: SegmentGroup = SegmentGroup(self.segments).start(lockstep=True)

    def on_cycle(self, after: Callable[[float], None]) -> Callable[[float], None]:
        return self.group.stepped_before(after)

    def trip_fault(self, node: int) -> float:
        tripped = time.monotonic()
        self.segments[0].drives[node].trip_fault()
        return tripped

    def check(self) -> None:
        self.group.check()

    def stop(self) -> None:
        self.group.stop()


class SimProcess:
    """The drives in a child process, their buses linked to this process's ``buses``."""

    def __init__(self, buses: Buses, eds: str | None, drives: int, fd: bool) -> None:
        from ...drivers.link.inproc_link import InProcessLink
        self.node_ids = list(buses[0][1])
        self.stderr: list[str] = []  # the child's, kept for what check() says
        self._replies: queue.Queue[dict[str, Any] | None] = queue.Queue()
        self._ids = itertools.count(1)
        self._gone = False  # the child's answers ended (it ended or died)
        spec = {"buses": [[c, list(n)] for c, n in buses], "eds": eds, "drives": drives,
                "fd": fd}
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._sock = ours
        try:
            self.link = InProcessLink(ours, [c for c, _ in buses], fd=fd,
                                      name="demo-sim-link").start()
            try:
                # a session of its own: a Ctrl-C is the demo's to act on (its loop ends in
                # torque-off while the drives still answer), and the demo stops the child
                self._child = subprocess.Popen(
                    [sys.executable, "-m", __name__, "--link-fd", str(theirs.fileno()),
                     json.dumps(spec)],
                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                    text=True, pass_fds=(theirs.fileno(),), start_new_session=True)
            except BaseException:
                self.link.close()
                raise
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()
        assert self._child.stdout is not None and self._child.stderr is not None
        self._threads = [threading.Thread(target=self._read_replies, args=(self._child.stdout,),
                                          name="demo-sim-replies", daemon=True),
                         threading.Thread(target=self._read_stderr, args=(self._child.stderr,),
                                          name="demo-sim-stderr", daemon=True)]
        for t in self._threads:
            t.start()
        self.pid: int | None = self._child.pid
        self.where = f"in a process of their own (pid {self.pid})"
        try:
            self._reply(0, START_TIMEOUT, "start")
        except BaseException:
            self.stop()
            raise

    def trip_fault(self, node: int) -> float:
        return float(self._request("trip_fault", node=node)["tripped"])

    def check(self) -> None:
        if self._child.poll() is not None:  # it ended before the demo stopped it
            raise SimulatorFailed(self._ended())
        self._request("check")

    def stop(self) -> None:
        """End the child (killed after STOP_TIMEOUT), then the link; idempotent."""
        child = self._child
        try:
            if child.poll() is None:
                self._send({"op": "stop", "id": 0})
                try:
                    child.wait(STOP_TIMEOUT)
                except subprocess.TimeoutExpired:
                    child.kill()
                    child.wait(STOP_TIMEOUT)
        finally:
            self.link.close()
            self._sock.close()
            for t in self._threads:
                t.join(1.0)
            for stream in (child.stdin, child.stdout, child.stderr):
                try:
                    if stream is not None:
                        stream.close()
                except OSError:  # unflushed lines to a child that died
                    pass

    def _send(self, request: dict[str, Any]) -> bool:
        stdin = self._child.stdin
        try:
            assert stdin is not None
            stdin.write(json.dumps(request) + "\n")
            stdin.flush()
            return True
        except (OSError, ValueError):  # it ended (a broken pipe), or stdin closed
            return False

    def _request(self, op: str, **args: Any) -> dict[str, Any]:
        ident = next(self._ids)
        if self._gone or not self._send({"op": op, "id": ident, **args}):
            raise SimulatorFailed(self._ended())
        return self._reply(ident, REPLY_TIMEOUT, op)

    def _reply(self, ident: int, timeout: float, what: str) -> dict[str, Any]:
        """The answer to request ``ident``: one that came late to an earlier request (after
        its timeout) is passed over."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                reply = self._replies.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise SimulatorFailed(f"simulator process: no answer to {what} in "
                                      f"{timeout:g} s") from None
            if reply is None:
                raise SimulatorFailed(self._ended())
            if reply.get("id") == ident:
                break
        if not reply.get("ok"):
            raise SimulatorFailed(f"simulator process: {what} failed: {reply.get('error')}")
        return reply

    def _ended(self) -> str:
        try:
            code = self._child.wait(1.0)
        except subprocess.TimeoutExpired:
            code = None
        last = "; ".join(self.stderr[-3:])
        return (f"simulator process ended (exit code {code})" + (f": {last}" if last else ""))

    def _read_replies(self, stream: IO[str]) -> None:
        try:
            for line in stream:
                try:
                    self._replies.put(json.loads(line))
                except ValueError:
                    self.stderr.append(line.rstrip())
        except (OSError, ValueError):  # closed by stop()
            pass
        self._gone = True
        self._replies.put(None)

    def _read_stderr(self, stream: IO[str]) -> None:
        try:
            for line in stream:
                self.stderr.append(line.rstrip())
                sys.stderr.write(f"rocoma-can demo (simulator): {line}")
        except (OSError, ValueError):  # closed by stop()
            pass


def _serve(sim: InProcessSim, done: threading.Event) -> None:
    """The child's requests, one JSON line each on stdin, until ``stop`` or its end."""
    def answer(reply: dict[str, Any]) -> None:
        sys.stdout.write(json.dumps(reply) + "\n")
        sys.stdout.flush()

    try:
        answer({"ok": True, "id": 0})  # started
        for line in sys.stdin:
            ident = None
            try:
                request = json.loads(line)
                op, ident = request["op"], request.get("id")
                if op == "stop":
                    return
                if op == "trip_fault":
                    answer({"ok": True, "id": ident,
                            "tripped": sim.trip_fault(int(request["node"]))})
                elif op == "check":
                    sim.check()
                    answer({"ok": True, "id": ident})
                else:
                    answer({"ok": False, "id": ident, "error": f"unknown request {op!r}"})
            except Exception as exc:  # noqa: BLE001 - the demo reports it
                answer({"ok": False, "id": ident, "error": f"{type(exc).__name__}: {exc}"})
    finally:
        done.set()


def child_main(argv: Sequence[str] | None = None) -> int:
    """The child: ``--link-fd FD SPEC`` (SPEC: the JSON SimProcess writes)."""
    import argparse

    from ...drivers.link.inproc_link import InProcessLink
    from .config import emulate
    # The demo ends this process (stop, its stdin's end, the link's); a stop signal to
    # every process of a service is the demo's to act on, while the drives answer its
    # loop's torque-off frames.
    for stop in (signal.SIGINT, signal.SIGTERM):
        signal.signal(stop, signal.SIG_IGN)
    p = argparse.ArgumentParser(prog=f"python -m {__name__}")
    p.add_argument("--link-fd", type=int, required=True)
    p.add_argument("spec")
    args = p.parse_args(argv)
    spec = json.loads(args.spec)
    buses = [(str(c), [int(n) for n in nodes]) for c, nodes in spec["buses"]]
    fd = bool(spec["fd"])
    emulated = emulate(spec["eds"], int(spec["drives"])) if spec["eds"] else None
    sock = socket.socket(fileno=args.link_fd)
    done = threading.Event()
    # the link first: the drives' boot-up frames must reach the demo
    link = InProcessLink(sock, [c for c, _ in buses], fd=fd, on_close=done.set)
    try:
        # This thread reads the link and, at once, steps the drives that got frames
        # (lockstep_pass, as the demo's loop steps them in its own process): no hand-over
        # to a receive thread between a SYNC's arrival and its answer. The group's thread
        # and timers take over only when no frame came for a while (the loop stopped).
        sim = InProcessSim(buses, "inproc", emulated, fd)
        try:
            threading.Thread(target=_serve, args=(sim, done), name="sim-requests",
                             daemon=True).start()
            while not done.is_set():
                if link.receive(LINK_IDLE):
                    sim.group.lockstep_pass()
        finally:
            sim.stop()
    finally:
        link.close()
        sock.close()
    return 0


if __name__ == "__main__":
    sys.exit(child_main())
