"""The hints the verbs' refusals carry: what lifts a refusal (``with_clear_hint``), what to
do on a host without SocketCAN or without the link asked for (``no_socketcan_hint``)."""
from __future__ import annotations

import errno

from ..events import LATCHED


def with_clear_hint(reason: str) -> str:
    """A refusal, pointing to the verb that lifts it where the e-stop latch is why."""
    return reason + (" (rocoma-can clear clears it)" if LATCHED in reason else "")


#: what to do instead of ``run`` on a kernel without SocketCAN
RUN_ELSEWHERE = ("on vcan, from a checkout, tools/vcan-run -- rocoma-can run CONFIG with "
                 "channel: vcan0; without a kernel bus, rocoma-can demo, or interface: "
                 "virtual in CONFIG")
#: what to do instead of a verb that reaches a running manager's bus (status, record ...)
REACH_ELSEWHERE = ("run it where the manager's bus is: the robot's computer, or on vcan, from "
                   "a checkout, inside tools/vcan-run beside the manager")


def no_socketcan_hint(exc: BaseException, instead: str = RUN_ELSEWHERE) -> str:
    """What to do when the kernel has no SocketCAN (EAFNOSUPPORT: containers, WSL, macOS;
    ``instead`` says what), or no such link (ENODEV: a typo, an adapter not plugged in, vcan
    not made), which a new user meets first as an errno: its words say nothing about CAN."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, OSError) and seen.errno == errno.EAFNOSUPPORT:
            return f"; this kernel has no SocketCAN (AF_CAN): {instead}"
        if isinstance(seen, OSError) and seen.errno == errno.ENODEV:
            return ("; no such network interface: `ip link` lists them (an adapter plugged "
                    "in, its driver loaded?); rocoma-can doctor CONFIG checks each bus and "
                    "says how to create or raise it")
        seen = seen.__cause__ or seen.__context__
    return ""

