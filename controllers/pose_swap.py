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


@dataclass(frozen=True)
class PoseSwapState(SwapState):
    """Copies taken on the switcher thread (arrays in the order of ``names``)."""
    names: tuple[str, ...]
    reference: np.ndarray           # rad, the reference the predecessor was tracking
    reference_velocity: np.ndarray  # rad/s
    target: np.ndarray              # rad, where the predecessor was going
    measured: np.ndarray            # rad, measured position when the state was taken

    def fill(self, field: str, names: tuple[str, ...], out: np.ndarray) -> np.ndarray:
        """Copy ``field`` for the joints in ``names`` that this state knows into ``out``
        (others keep their value); returns a bool mask of the joints filled."""
        values = getattr(self, field)
        filled = np.zeros(len(names), dtype=bool)
        for i, name in enumerate(names):
            if name in self.names:
                out[i] = values[self.names.index(name)]
                filled[i] = True
        return filled


def find_pose_state(swap_state: SwapState | None) -> PoseSwapState | None:
    """The PoseSwapState in ``swap_state``, looking inside a tuple's state if needed.

    A ControllerTuple hands over the swap states of its members; any object with a
    ``states`` sequence (or mapping) is searched, merging the members' joints.
    """
    if isinstance(swap_state, PoseSwapState):
        return swap_state
    members = getattr(swap_state, "states", None)
    if isinstance(members, dict):
        members = list(members.values())
    poses = [find_pose_state(s) for s in members or ()]
    poses = [p for p in poses if p is not None]
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
