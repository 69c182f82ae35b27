"""The three controller layers a user implements (rocoma's "adaptee" interfaces).

Separate base classes keep a controller out of a layer it was not written for: the manager
refuses an EmergencyController as a normal controller and a plain Controller as an emergency
controller (TypeError), as rocoma does with its separate interfaces.

Everything a controller needs from the manager is set as attributes before ``create`` runs:
``name``, ``dt``, ``state`` and ``command`` (the objects shared by all controllers of one
manager) and ``workers`` (its own WorkerManager; not for failproof controllers).

User callbacks return ``True`` on success. ``False`` or an exception is a failure; the adapter
turns an exception into a logged ``False`` so no user code can take the manager down.

The layers are generic in the types of ``state`` and ``command`` because the core runs any
robot and cannot name a CAN robot's types: a controller says what it reads and writes,
``class Hold(Controller[JointState, JointCommand])``, and mypy checks its use of them. A bare
``class Hold(Controller)`` means ``Controller[Any, Any]``: untyped code works as before.
"""
from __future__ import annotations

import abc
from typing import TYPE_CHECKING, Any, Generic

from typing_extensions import TypeVar  # a default (PEP 696) before Python 3.13

if TYPE_CHECKING:
    from .workers import HandleOrName, WorkerHandle, WorkerManager, WorkerOptions

StateT = TypeVar("StateT", default=Any)
CommandT = TypeVar("CommandT", default=Any)


class SwapState:
    """Data an outgoing controller hands to its successor during a switch.

    Subclass it with whatever the successor needs (rocoma's ControllerSwapStateInterface);
    the successor checks the type with ``isinstance`` because it may come from any controller.
    """


class _Unset:
    """The type of ``state``/``command`` before the manager set them: None cannot mark
    that, a manager given no state object (the default) sets None."""


_UNSET = _Unset()


class _Named(Generic[StateT, CommandT]):
    """What all layers share: a name and the manager's state/command objects."""

    #: Joint feedback the controller cannot work without ("position", "velocity",
    #: "torque"): a config whose drives do not all report it is refused when the controller
    #: is loaded (a drive whose file has no 0x6077 reports no torque; JointState.torque
    #: would read 0 for it, silently).
    feedback_needed: frozenset[str] = frozenset()

    def __init__(self, name: str | None = None) -> None:
        self.name: str = name or type(self).__name__
        self.dt: float = 0.0
        self._state: StateT | _Unset = _UNSET
        self._command: CommandT | _Unset = _UNSET

    # Properties, not plain attributes, so that their type can be StateT and CommandT
    # without pretending the None they held before the manager set them was one: reading
    # them before that is a clear error instead of an AttributeError on None later.
    @property
    def state(self) -> StateT:
        """The manager's state object (on a CAN bus a drivers.protocol.joints.JointState)."""
        if isinstance(self._state, _Unset):
            raise self._unattached("state")
        return self._state

    @state.setter
    def state(self, state: StateT) -> None:
        self._state = state

    @property
    def command(self) -> CommandT:
        """The manager's command object (on a CAN bus a drivers.protocol.joints.JointCommand)."""
        if isinstance(self._command, _Unset):
            raise self._unattached("command")
        return self._command

    @command.setter
    def command(self, command: CommandT) -> None:
        self._command = command

    def _unattached(self, what: str) -> RuntimeError:
        return RuntimeError(f"controller {self.name!r} has no {what} yet: "
                            "add it to a ControllerManager first")

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r})"

    def create(self, dt: float) -> bool:
        """Allocate what the controller needs (use instead of __init__ for heavy work)."""
        return True

    def cleanup(self) -> bool:
        """Free what create allocated (use instead of __del__)."""
        return True


class Controller(_Named[StateT, CommandT], abc.ABC):
    """A controller that can be switched to at run time; it may fail or raise."""

    def __init__(self, name: str | None = None) -> None:
        super().__init__(name)
        self.workers: WorkerManager | None = None
        self._initialized: bool = False  # kept in step by the adapter (rocoma's isInitialized)

    @property
    def is_initialized(self) -> bool:
        """True between a successful initialize/reset/swap and the end of stop."""
        return self._initialized

    @abc.abstractmethod
    def initialize(self, dt: float) -> bool:
        """Prepare to run; may take many cycles (it runs on the switcher thread)."""

    @abc.abstractmethod
    def advance(self, dt: float) -> bool:
        """One control cycle: read ``self.state``, write ``self.command``."""

    def reset(self, dt: float) -> bool:
        """Called instead of initialize when already initialized."""
        return self.initialize(dt)

    def pre_stop(self) -> bool:
        """Prepare for stop (e.g. cancel workers); runs off the update thread."""
        return True

    def stop(self) -> bool:
        """Stop the controller; runs on the stopper thread, never in the update thread."""
        return True

    def swap(self, dt: float, swap_state: SwapState | None) -> bool:
        """Take over from another controller; by default reset or initialize."""
        return self.reset(dt) if self.is_initialized else self.initialize(dt)

    def get_swap_state(self) -> SwapState | None:
        """What the successor should know about this controller (None: nothing)."""
        return None

    # Workers (rocoma's worker extension), delegated to this controller's WorkerManager.
    def add_worker(self, options: WorkerOptions) -> WorkerHandle:
        return self._worker_manager().add_worker(options)

    def start_worker(self, handle: HandleOrName) -> bool:
        return self._worker_manager().start_worker(handle)

    def cancel_worker(self, handle: HandleOrName, wait: bool = True,
                      timeout: float = 1.0) -> bool:
        return self._worker_manager().cancel_worker(handle, wait=wait, timeout=timeout)

    def _worker_manager(self) -> WorkerManager:
        if self.workers is None:
            raise RuntimeError(f"controller {self.name!r} has no worker manager: "
                               "add it to a ControllerManager first")
        return self.workers


class EmergencyController(Controller[StateT, CommandT]):
    """A smart-stop controller; it may fail, and then the failproof layer takes over."""

    @abc.abstractmethod
    def initialize_fast(self, dt: float) -> bool:
        """Take over within the cycle of the failure: must take far less than dt."""


class FailproofController(_Named[StateT, CommandT], abc.ABC):
    """The last layer. It has no initialize and cannot fail: advance returns nothing and the
    adapter swallows anything it raises."""

    @abc.abstractmethod
    def advance(self, dt: float) -> None:
        """Write the safe command into ``self.command``."""
