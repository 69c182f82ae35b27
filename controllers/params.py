"""Parameter checking shared by the controllers of this library.

Controllers are built from YAML as ``cls(name, **params)``, so a typo or a wrong sign must be
reported at construction with the controller, the parameter and the reason in the message.
Per-joint parameters take a scalar (same value for every joint) or a list with one value per
selected joint. The number of joints is only known once the manager has attached the state,
so a list's length is checked in ``create``, which raises ValueError (the manager's adapter
logs it and reports the create as failed).

Raw values are typed ``object``, not ``Any``: they come from YAML unchecked, so mypy makes a
controller pass them through these functions before it can compute with them.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from rocoma_can.drivers.protocol.joints import JointMode
from rocoma_can.errors import ParamError


class Owner(Protocol):
    """The controller a parameter belongs to: errors name it."""

    @property
    def name(self) -> str: ...


def param_error(owner: Owner, param: str, reason: str) -> ParamError:
    """The one error format: which controller, which parameter, what is wrong."""
    return ParamError(f"{type(owner).__name__} {owner.name!r}", param, reason)


def _as_float(owner: Owner, param: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise param_error(owner, param, f"expected a number, got {value!r}")
    return float(value)


def number(owner: Owner, param: str, value: object, *, minimum: float | None = None,
           positive: bool = False, allow_inf: bool = False) -> float:
    """A scalar parameter: finite unless allow_inf, >= minimum, > 0 if positive."""
    x = _as_float(owner, param, value)
    _check(owner, param, x, minimum=minimum, positive=positive, allow_inf=allow_inf)
    return x


def _check(owner: Owner, param: str, x: float, *, minimum: float | None, positive: bool,
           allow_inf: bool, where: str = "") -> None:
    if math.isnan(x) or (math.isinf(x) and not allow_inf):
        raise param_error(owner, param, f"must be finite{where}, got {x}")
    if positive and not x > 0:
        raise param_error(owner, param, f"must be > 0{where}, got {x}")
    if minimum is not None and x < minimum:
        raise param_error(owner, param, f"must be >= {minimum}{where}, got {x}")


@dataclass(frozen=True)
class PerJoint:
    """A validated per-joint parameter whose length is checked once the joints are known."""
    param: str
    values: tuple[float, ...]
    scalar: bool

    def resolve(self, owner: Owner, n: int) -> np.ndarray:
        """One float64 value per selected joint (a fresh array the controller may keep)."""
        if self.scalar:
            return np.full(n, self.values[0])
        if len(self.values) != n:
            raise param_error(owner, self.param,
                              f"has {len(self.values)} values but the controller drives "
                              f"{n} joints; give a scalar or one value per joint")
        return np.array(self.values, dtype=float)


def per_joint(owner: Owner, param: str, value: object, *, minimum: float | None = None,
              positive: bool = False, allow_inf: bool = False) -> PerJoint:
    """A scalar or a non-empty list of numbers, each checked like ``number``."""
    if isinstance(value, (list, tuple, np.ndarray)):
        if len(value) == 0:
            raise param_error(owner, param, "the list is empty")
        values = tuple(_as_float(owner, param, v) for v in value)
        for i, x in enumerate(values):
            _check(owner, param, x, minimum=minimum, positive=positive, allow_inf=allow_inf,
                   where=f" (element {i})")
        return PerJoint(param, values, scalar=False)
    x = number(owner, param, value, minimum=minimum, positive=positive, allow_inf=allow_inf)
    return PerJoint(param, (x,), scalar=True)


def optional_per_joint(owner: Owner, param: str, value: object) -> PerJoint | None:
    """A per-joint pose that may be left out (None: use the measured position)."""
    return None if value is None else per_joint(owner, param, value)


def output_mode(owner: Owner, value: object, allowed: Iterable[JointMode],
                param: str = "mode") -> JointMode:
    """A CiA 402 mode given as a name ("CST", "csp") or a JointMode."""
    allowed = tuple(allowed)
    names = ", ".join(m.name for m in allowed)
    if isinstance(value, str):
        mode = JointMode.__members__.get(value.strip().upper())
    elif isinstance(value, JointMode):
        mode = value
    else:
        mode = None
    if mode not in allowed:
        raise param_error(owner, param, f"must be one of {names}, got {value!r}")
    return mode


def choice(owner: Owner, param: str, value: object, allowed: Sequence[str]) -> str:
    if not isinstance(value, str) or value not in allowed:
        raise param_error(owner, param, f"must be one of {', '.join(allowed)}, got {value!r}")
    return value


def joint_names(owner: Owner, value: object) -> tuple[str, ...] | None:
    """The ``joints`` parameter: None (all joints) or a non-empty list of unique names."""
    if value is None:
        return None
    if isinstance(value, str) or not isinstance(value, (list, tuple)):
        raise param_error(owner, "joints", f"expected a list of joint names, got {value!r}")
    if not value:
        raise param_error(owner, "joints", "the list is empty (leave it out for all joints)")
    for name in value:
        if not isinstance(name, str) or not name:
            raise param_error(owner, "joints", f"joint names must be non-empty strings, "
                                               f"got {name!r}")
    if len(set(value)) != len(value):
        raise param_error(owner, "joints", f"names must be unique, got {list(value)}")
    return tuple(value)
