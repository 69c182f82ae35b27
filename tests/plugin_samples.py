"""Controller classes for tests/test_plugins.py, named in configs as "plugin_samples:<Class>"."""
from __future__ import annotations

from rocoma_can.interfaces import Controller, EmergencyController


class Gains(Controller):
    """A controller with keyword parameters and a checked one (kp > 0)."""

    def __init__(self, name: str, *, kp: float, kd: float = 1.0) -> None:
        super().__init__(name)
        if not kp > 0:
            raise ValueError(f"Gains {name!r}: parameter 'kp': must be > 0, got {kp}")
        self.kp = kp
        self.kd = kd

    def initialize(self, dt: float) -> bool:
        return True

    def advance(self, dt: float) -> bool:
        return True


class Brake(EmergencyController):
    def __init__(self, name: str, gain: float = 1.0) -> None:
        super().__init__(name)
        self.gain = gain

    def initialize(self, dt: float) -> bool:
        return True

    def initialize_fast(self, dt: float) -> bool:
        return True

    def advance(self, dt: float) -> bool:
        return True


class Renamed(Gains):
    """Ignores the name it is given (the config's name must win)."""

    def __init__(self, name: str) -> None:
        super().__init__("something_else", kp=1.0)


class Unfinished(Controller):
    """Forgot advance: abstract."""

    def initialize(self, dt: float) -> bool:
        return True


class NotAController:
    def __init__(self, name: str) -> None:
        self.name = name


class Outer:
    class Inner(Gains):
        """Reached as "plugin_samples:Outer.Inner"."""


NOT_A_CLASS = 42
