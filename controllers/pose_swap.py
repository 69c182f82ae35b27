"""The swap state the position controllers of this library hand to each other.

The PD and trajectory controllers return a PoseSwapState from ``get_swap_state`` and accept
one in ``swap``: the successor starts its reference where the predecessor's reference was, so
a switch does not jump. Entries are keyed by joint name, so a controller of a tuple that
drives only some joints picks its own.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rocoma_can.interfaces import SwapState
from rocoma_can.tuples import TupleSwapState


@dataclass(frozen=True)
class PoseSwapState(SwapState):
    """Copies taken on the switcher thread (arrays in the order of ``names``)."""
    names: tuple[str, ...]
    reference: np.ndarray           # rad, the reference the predecessor was tracking
    reference_velocity: np.ndarray  # rad/s
    target: np.ndarray              # rad, where the predecessor was going
    measured: np.ndarray            # rad, measured position when the state was taken

    def fill(self, field: str, names: tuple[str, ...], out: np.ndarray) -> None:
        """Copy ``field`` into ``out`` for the joints of ``names`` that this state knows
        (the others keep their value)."""
        values = getattr(self, field)
        for i, name in enumerate(names):
            if name in self.names:
                out[i] = values[self.names.index(name)]


def find_pose_state(swap_state: SwapState | None) -> PoseSwapState | None:
    """The PoseSwapState in ``swap_state``; a tuple's members' pose states are merged."""
    if isinstance(swap_state, PoseSwapState):
        return swap_state
    if not isinstance(swap_state, TupleSwapState):
        return None
    poses = [p for p in map(find_pose_state, swap_state.states) if p is not None]
    if not poses:
        return None
    if len(poses) == 1:
        return poses[0]
    return PoseSwapState(
        names=tuple(n for p in poses for n in p.names),
        reference=np.concatenate([p.reference for p in poses]),
        reference_velocity=np.concatenate([p.reference_velocity for p in poses]),
        target=np.concatenate([p.target for p in poses]),
        measured=np.concatenate([p.measured for p in poses]),
    )
