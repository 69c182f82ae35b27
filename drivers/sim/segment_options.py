"""How a simulated segment's drives are made and run: SimulatedSegment's options, checked.

One frozen dataclass instead of a dozen keyword arguments: ``SimulatedSegment.open`` takes
them as keywords (``SimulatedSegment.open(channel, "inproc", (1, 2), sync_period=0.001)``)
and builds these, and a test or tool that makes several alike segments passes one.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from ..files.identity import Identity
from .dynamics import JointParams
from .objects import MAX_AXES

#: joint physics and gains: one for every joint, or per node id / (node id, axis) pair
Params = JointParams | Mapping[int | tuple[int, int], JointParams]


@dataclass(frozen=True)
class SegmentOptions:
    """``eds_path``: the drives' file (None: the CiA 402 drive shipped with the package).

    ``params`` gives the joint physics and loop gains: one JointParams for every joint, or
    a mapping whose key is a node id (every axis of that node) or a (node id, axis) pair
    (that axis; it wins over the node's). Joints not in it get the defaults.

    Time: ``sync_period`` (s) fixes each SYNC's step (deterministic runs; None: the time
    since the previous SYNC, at most ``max_dt``); without it the drives keep running every
    ``free_run_period`` between SYNCs. ``seed``: the noise's. ``fd``: the drives answer in
    CAN FD frames and map PDOs of up to 64 bytes.

    ``increments_per_rev``, ``rated_torque_nm``: what the drives assume where the file
    states no scaling; ``overrides``: object values ((index, subindex) -> value) that
    replace the file's on every drive.

    ``axes`` maps a node id to its number of CiA 402 axes (1..8, CiA 402-2: axis n's
    objects at +0x800 (n - 1) in the same file; nodes not in it have one).

    ``identities`` maps a node id to its identity object (0x1018: vendor-ID, product code,
    revision, serial number; the fields given replace the file's). A node not in it answers
    the file's values, with a serial number of its own (the file's plus node id - 1, or the
    node id where the file gives none).

    ``unconfigured``: further nodes without a node id (CiA 305: 0xFF), one per identity,
    which must give the serial number (the other fields default as above). Each answers
    nothing but LSS until it is given a node id (lss.py); its joints come after the
    configured nodes'.
    """
    eds_path: str | None = None
    params: Params | None = None
    sync_period: float | None = None
    max_dt: float = 0.05
    free_run_period: float | None = 0.05
    seed: int = 0
    fd: bool = False
    increments_per_rev: int = 1 << 20
    rated_torque_nm: float = 1.0
    overrides: Mapping[tuple[int, int], Any] = field(default_factory=dict)
    axes: Mapping[int, int] = field(default_factory=dict)
    identities: Mapping[int, Identity] = field(default_factory=dict)
    unconfigured: tuple[Identity, ...] = ()

    @classmethod
    def of(cls, *, overrides: Mapping[tuple[int, int], Any] | None = None,
           axes: Mapping[int, int] | None = None,
           identities: Mapping[int, Identity] | None = None,
           unconfigured: Iterable[Identity] = (), **rest: Any) -> SegmentOptions:
        """From keywords as ``SimulatedSegment.open`` takes them (None for an empty
        mapping, any iterable of unconfigured identities)."""
        return cls(overrides=dict(overrides or {}), axes=dict(axes or {}),
                   identities=dict(identities or {}), unconfigured=tuple(unconfigured),
                   **rest)

    def check(self, node_ids: list[int]) -> None:
        """ValueError for options that cannot make a segment of ``node_ids``."""
        if not node_ids and not self.unconfigured:
            raise ValueError("a simulated segment needs at least one node")
        if any(i.serial is None for i in self.unconfigured):
            raise ValueError("an unconfigured node needs a serial number (its LSS address "
                             "tells it from the others)")
        bad = [n for n in node_ids if not 1 <= n <= 127]
        if bad:
            raise ValueError(f"CANopen node ids must be 1..127, got {bad}")
        if self.sync_period is not None and not 0 < self.sync_period <= 1:
            raise ValueError(f"sync_period must be in (0, 1] s, got {self.sync_period}")
        if not 0 < self.max_dt <= 1:
            raise ValueError(f"max_dt must be in (0, 1] s, got {self.max_dt}")
        for what, given in (("identities", self.identities), ("axes", self.axes)):
            strays = sorted(set(given) - set(node_ids))
            if strays:
                raise ValueError(f"{what} given for node ids {strays}, which are not "
                                 "simulated")
        bad_axes = {n: a for n, a in self.axes.items() if not 1 <= a <= MAX_AXES}
        if bad_axes:
            raise ValueError(f"a node has 1..{MAX_AXES} axes, got {bad_axes}")

    def check_scaling(self) -> None:
        """ValueError for a scaling the drives cannot assume."""
        if not isinstance(self.increments_per_rev, int) or self.increments_per_rev <= 0 \
                or not self.rated_torque_nm > 0:
            raise ValueError("increments_per_rev must be a positive integer and "
                             f"rated_torque_nm > 0, got {self.increments_per_rev!r}, "
                             f"{self.rated_torque_nm!r}")

    def joint_params(self, joints: list[tuple[int, int]]) -> list[JointParams]:
        """Each joint's (node id, axis) physics, then the unconfigured nodes' (defaults)."""
        params = self.params
        if isinstance(params, Mapping):
            chosen = [params.get((n, a), params.get(n, JointParams())) for n, a in joints]
        else:
            chosen = [params or JointParams()] * len(joints)
        return chosen + [JointParams()] * len(self.unconfigured)
