"""A SocketCAN link as the kernel reports it, read and never changed (``rocoma-can doctor``).

The bit rate, the controller state, the error counters and restart-ms are only in netlink,
which iproute2 prints as JSON (``ip -details -statistics -json link show DEV``); whether the
link exists, is up, its type, MTU and transmit queue length are also in
/sys/class/net/DEV, so a host without iproute2 is still judged on those. Parsing is a pure
function of the text, so it is tested against output captured from real kernels.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: ARPHRD_CAN (linux/if_arp.h): /sys/class/net/DEV/type of every CAN link, vcan too
ARPHRD_CAN = 280
#: /sys/class/net/DEV/type -> the name ``ip -json`` gives the link type (link_type)
LINK_TYPES = {ARPHRD_CAN: "can", 1: "ether", 772: "loopback"}
#: a link that carries CAN FD frames (linux/can.h CANFD_MTU); classic CAN is 16
CANFD_MTU = 72
SYSFS_NET = Path("/sys/class/net")
IFF_UP = 0x1
#: how to get ``ip`` where it is missing (Debian, Ubuntu; iproute2 elsewhere too)
IPROUTE2_INSTALL = "sudo apt-get install iproute2"
_UPDATE = "an iproute2 with JSON output (4.14 or later): sudo apt-get install iproute2"
#: seconds ``ip`` may take to answer (it reads one link; a hung netlink must not hang us)
IP_TIMEOUT = 5.0
#: where ``ip`` lives (sbin is often not on a user's PATH)
_SBIN = "/usr/local/sbin:/usr/sbin:/sbin"


@dataclass(frozen=True)
class CanLink:
    """What one link is. None: not reported (no iproute2, or the driver does not say)."""
    name: str
    up: bool                         # administratively up (IFF_UP)
    operstate: str                   # the kernel's: UP, DOWN (bus-off too), UNKNOWN (vcan)
    mtu: int
    txqueuelen: int | None
    kind: str | None = None          # "can" (a controller), "vcan", "vxcan", ...
    state: str | None = None         # ERROR-ACTIVE, ERROR-WARNING, ERROR-PASSIVE, BUS-OFF, ...
    bitrate: int | None = None       # bit/s of the arbitration phase (0: never set)
    data_bitrate: int | None = None  # CAN FD data phase
    ctrlmode: tuple[str, ...] = ()   # FD, LISTEN-ONLY, ONE-SHOT, ...
    restart_ms: int | None = None    # automatic restart after bus-off (0: none)
    berr: tuple[int, int] | None = None  # the controller's (tx, rx) error counters
    counters: Mapping[str, int] = field(default_factory=dict)  # bus_off, tx_errors, ...
    #: the kernel's link type: "can" (ARPHRD_CAN), "ether", "loopback", ... (None: not said)
    link_type: str | None = None

    @property
    def fd(self) -> bool:
        return "FD" in self.ctrlmode

    @property
    def is_can(self) -> bool:
        """A CAN link (ARPHRD_CAN: a controller, vcan, vxcan), as the kernel says; a link
        whose type is not known is given the benefit of the doubt (the bus says more)."""
        return self.link_type in (None, "can")


def _int(value: Any) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def parse_ip_link(text: str) -> CanLink:
    """The link in ``ip -details -statistics -json link show DEV`` output. ValueError when
    the text is not one link's JSON (another ``ip``'s output, a truncated answer)."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"not JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(data, list) or len(data) != 1 or not isinstance(data[0], dict):
        raise ValueError("expected a list of one link")
    link: dict[str, Any] = data[0]
    info = link.get("linkinfo") or {}
    can = info.get("info_data") or {}
    # a controller with fixed bit rates reports the one set as bittiming_bitrate
    timing, data_timing = can.get("bittiming") or {}, can.get("data_bittiming") or {}
    bitrate = _int(timing.get("bitrate", can.get("bittiming_bitrate")))
    data_bitrate = _int(data_timing.get("bitrate", can.get("data_bittiming_bitrate")))
    berr = can.get("berr_counter")
    counters: dict[str, int] = {}
    for key, value in (info.get("info_xstats") or {}).items():
        if _int(value) is not None:
            counters[key] = value
    stats = link.get("stats64") or link.get("stats") or {}
    for direction in ("tx", "rx"):
        for key in ("errors", "dropped"):
            value = _int((stats.get(direction) or {}).get(key))
            if value is not None:
                counters[f"{direction}_{key}"] = value
    return CanLink(
        name=str(link.get("ifname", "")),
        up="UP" in (link.get("flags") or ()),
        operstate=str(link.get("operstate", "UNKNOWN")),
        mtu=_int(link.get("mtu")) or 0,
        txqueuelen=_int(link.get("txqlen")),
        kind=info.get("info_kind"),
        state=can.get("state"),
        bitrate=bitrate,
        data_bitrate=data_bitrate,
        ctrlmode=tuple(str(m) for m in can.get("ctrlmode") or ()),
        restart_ms=_int(can.get("restart_ms")),
        berr=(int(berr["tx"]), int(berr["rx"])) if isinstance(berr, dict) else None,
        counters=counters,
        link_type=str(link["link_type"]) if isinstance(link.get("link_type"), str) else None,
    )


def _read(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except OSError:
        return None


def from_sysfs(name: str, root: Path = SYSFS_NET) -> CanLink | None:
    """What sysfs says of the link, None when it does not exist."""
    base = root / name
    flags, mtu = _read(base / "flags"), _read(base / "mtu")
    if flags is None or mtu is None:
        return None
    queue, number = _read(base / "tx_queue_len"), _read(base / "type")
    link_type = None
    if number is not None and number.isdigit():
        link_type = LINK_TYPES.get(int(number), f"type {number}")
    return CanLink(name=name, up=bool(int(flags, 16) & IFF_UP),
                   operstate=(_read(base / "operstate") or "unknown").upper(),
                   mtu=int(mtu), txqueuelen=int(queue) if queue else None,
                   link_type=link_type)


def can_interfaces(root: Path = SYSFS_NET) -> list[str]:
    """Every CAN link of this host (type ARPHRD_CAN), sorted by name."""
    try:
        names = sorted(p.name for p in root.iterdir())
    except OSError:
        return []
    return [n for n in names if (link := from_sysfs(n, root)) is not None
            and link.link_type == LINK_TYPES[ARPHRD_CAN]]


def socketcan_in_kernel() -> bool:
    """Whether this kernel has SocketCAN (AF_CAN): containers, WSL and macOS often do not."""
    import socket
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except (OSError, AttributeError):
        return False
    return True


def ip_command() -> str | None:
    return shutil.which("ip", path=os.environ.get("PATH", "") + ":" + _SBIN)


@dataclass(frozen=True)
class LinkReading:
    """A link read from this host: ``link`` None when it does not exist; ``unread`` says
    why netlink's part (bit rate, state, counters) is missing, "" when it is there, and
    ``fix`` how to get it."""
    name: str
    link: CanLink | None
    unread: str = ""
    fix: str = ""


def read_link(name: str, root: Path = SYSFS_NET) -> LinkReading:
    """The link as sysfs and, where it is installed, iproute2 report it."""
    basic = from_sysfs(name, root)
    if basic is None:
        return LinkReading(name, None)
    ip = ip_command()
    if ip is None:
        return LinkReading(name, basic, "iproute2 (ip) is not installed", IPROUTE2_INSTALL)
    try:
        done = subprocess.run([ip, "-details", "-statistics", "-json", "link", "show", name],
                              capture_output=True, text=True, timeout=IP_TIMEOUT, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return LinkReading(name, basic, f"{ip} failed: {exc}", _UPDATE)
    if done.returncode != 0:
        return LinkReading(name, basic, f"{ip} failed: {done.stderr.strip()}", _UPDATE)
    try:
        return LinkReading(name, parse_ip_link(done.stdout))
    except ValueError as exc:
        return LinkReading(name, basic, f"{ip}'s output not understood: {exc}", _UPDATE)
