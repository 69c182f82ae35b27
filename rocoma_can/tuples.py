"""Controller tuples: n controllers run as one, in order (rocoma's roco::ControllerTuple).

Typical use: one controller for the legs and one for the arm, switched together.

Order and failure, as in rocoma: create, initialize, reset, swap, initialize_fast and advance
call the members in order and stop at the first failure; the members after it are not called
and the tuple's call fails. pre_stop, stop and cleanup differ on purpose: they reach every
member even after one failed or raised (the exception is logged), because a member left
running after its tuple was stopped is a safety problem, not a tidiness one.

Shared objects: the manager sets ``dt``, ``state``, ``command`` and ``workers`` on the tuple
before create; each assignment is passed on to every member, so members read and write the
same state and command and register workers with the tuple's WorkerManager (member worker
names must therefore be distinct). Members keep their own names.

Swap states: ``get_swap_state`` returns a TupleSwapState with one slot per member, by
position. ``swap`` hands a TupleSwapState with as many slots as the tuple has members out by
position (a tuple switching to a tuple of the same shape, e.g. legs+arm to legs+arm); any
other state — a single controller's, or a tuple's of another size — goes to every member
whole, as rocoma does, and a member that cares looks inside with ``TupleSwapState.find``.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any, ClassVar, TypeVar, cast

from .interfaces import CommandT, Controller, EmergencyController, StateT, SwapState

log = logging.getLogger(__name__)

S = TypeVar("S", bound=SwapState)

#: Attributes the manager sets on a controller that the members must share.
SHARED_ATTRIBUTES = frozenset({"dt", "state", "command", "workers"})


class TupleSwapState(SwapState):
    """The swap states of a tuple's members, one slot per member (None: nothing to pass)."""

    def __init__(self, states: Sequence[SwapState | None]) -> None:
        self.states: tuple[SwapState | None, ...] = tuple(states)

    def __len__(self) -> int:
        return len(self.states)

    def find(self, kind: type[S]) -> S | None:
        """The first slot that is a ``kind`` (for a member handed a whole tuple's state)."""
        return next((s for s in self.states if isinstance(s, kind)), None)

    def __repr__(self) -> str:
        return f"TupleSwapState({list(self.states)!r})"


class ControllerTuple(Controller[StateT, CommandT]):
    """Members run in the order given; the tuple fails as soon as one member fails."""

    MEMBER_TYPE: ClassVar[type] = Controller

    def __init__(self, name: str, controllers: Sequence[Controller[StateT, CommandT]]) -> None:
        super().__init__(name)
        members = tuple(controllers)
        if not members:
            raise ValueError(f"controller tuple {name!r} needs at least one member")
        seen: dict[str, Controller[StateT, CommandT]] = {}
        for i, member in enumerate(members):
            if not isinstance(member, self.MEMBER_TYPE):
                raise TypeError(f"controller tuple {name!r}: member {i} ({member!r}) is not "
                                f"an instance of {self.MEMBER_TYPE.__name__}")
            if member.name in seen:
                raise ValueError(f"controller tuple {name!r}: two members named "
                                 f"{member.name!r}; member names must be distinct")
            seen[member.name] = member
        self._members = members
        #: Name of the member whose advance failed last (read it after the tuple failed).
        self.failed_member: str | None = None

    def __setattr__(self, key: str, value: Any) -> None:
        super().__setattr__(key, value)
        if key in SHARED_ATTRIBUTES:
            for member in self.__dict__.get("_members", ()):
                setattr(member, key, value)

    @property
    def controllers(self) -> tuple[Controller[StateT, CommandT], ...]:
        return self._members

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r}, {[m.name for m in self._members]!r})"

    def create(self, dt: float) -> bool:
        return self._in_order("create", lambda m: m.create(dt))

    def initialize(self, dt: float) -> bool:
        return self._in_order("initialize", lambda m: m.initialize(dt), initializes=True)

    def reset(self, dt: float) -> bool:
        return self._in_order("reset", lambda m: m.reset(dt), initializes=True)

    def swap(self, dt: float, swap_state: SwapState | None) -> bool:
        if isinstance(swap_state, TupleSwapState) and len(swap_state) == len(self._members):
            slots = iter(swap_state.states)
            return self._in_order("swap", lambda m: m.swap(dt, next(slots)), initializes=True)
        return self._in_order("swap", lambda m: m.swap(dt, swap_state), initializes=True)

    def get_swap_state(self) -> TupleSwapState:
        return TupleSwapState([m.get_swap_state() for m in self._members])

    def advance(self, dt: float) -> bool:
        # Hot path: no allocation, no logging; the failing member is recorded by name.
        for member in self._members:
            if not member.advance(dt):
                self.failed_member = member.name
                return False
        return True

    def pre_stop(self) -> bool:
        return self._every("pre_stop", lambda m: m.pre_stop())

    def stop(self) -> bool:
        ok = self._every("stop", lambda m: m.stop())
        for member in self._members:
            member._initialized = False
        return ok

    def cleanup(self) -> bool:
        return self._every("cleanup", lambda m: m.cleanup())

    def _in_order(self, call: str, fn: Callable[[Controller[StateT, CommandT]], Any],
                  initializes: bool = False) -> bool:
        """Call the members in order; stop at the first that fails (exceptions propagate
        to the tuple's adapter, which reports them as the tuple's failure)."""
        for member in self._members:
            ok = bool(fn(member))
            if initializes:
                # What an adapter does for a controller it calls (members have none), so a
                # member's default swap can choose between reset and initialize.
                member._initialized = ok
            if not ok:
                log.error("controller tuple %r: %s of member %r failed; the members after "
                          "it were not called", self.name, call, member.name)
                return False
        return True

    def _every(self, call: str, fn: Callable[[Controller[StateT, CommandT]], Any]) -> bool:
        ok = True
        for member in self._members:
            try:
                if not fn(member):
                    log.error("controller tuple %r: %s of member %r failed", self.name,
                              call, member.name)
                    ok = False
            except Exception:
                log.exception("controller tuple %r: %s of member %r raised; the other "
                              "members are still called", self.name, call, member.name)
                ok = False
        return ok


class EmergencyControllerTuple(ControllerTuple[StateT, CommandT],
                               EmergencyController[StateT, CommandT]):
    """A tuple of emergency controllers, itself usable as an emergency controller."""

    MEMBER_TYPE = EmergencyController

    def initialize_fast(self, dt: float) -> bool:
        # Runs in the update thread within the failure's cycle: no logging here.
        for member in self._members:
            ok = bool(cast("EmergencyController[StateT, CommandT]", member).initialize_fast(dt))
            member._initialized = ok
            if not ok:
                self.failed_member = member.name
                return False
        return True
