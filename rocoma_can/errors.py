"""One root for every error rocoma-can raises on purpose: ``except RocomaError`` catches them
all. Each also keeps the standard base it always had (ValueError for bad configuration,
RuntimeError for a refusing or silent manager), so code written against those still works."""
from __future__ import annotations


class RocomaError(Exception):
    """The root."""


class ConfigError(RocomaError, ValueError):
    """One or more problems, one per line, each starting with its YAML path."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = list(problems)
        super().__init__("\n".join(self.problems))


class PluginError(RocomaError, ValueError):
    """A controller entry that cannot be loaded; the message starts with its config path."""


class NoAnswer(RocomaError, RuntimeError):
    """The manager node did not answer (not running, wrong node id or channel)."""


class Refused(RocomaError, RuntimeError):
    """The manager node answered with an SDO abort: ``code``, and what it means."""

    def __init__(self, code: int, what: str, meaning: str = "see CiA 301") -> None:
        self.code = code
        super().__init__(f"{what}: refused by the manager (SDO abort 0x{code:08X}: {meaning})")


class HomingFailed(RocomaError, RuntimeError):
    """Homing of a drive did not end with it homed (the message names the drive and why)."""


class BusTaken(RocomaError, RuntimeError):
    """Another manager drives the bus (runtime/another_manager.py): what was heard there."""


class LssFailed(RocomaError, RuntimeError):
    """An LSS service (CiA 305) got no answer or an error answer; the message says which."""


class ParamError(RocomaError, ValueError):
    """A parameter that is wrong. It keeps the parameter's name and the reason apart, so a
    config loader can put the parameter in its path (``controllers[0].params.kp``) instead
    of a message about a constructor call."""

    def __init__(self, controller: str, param: str, reason: str) -> None:
        self.controller = controller
        self.param = param
        self.reason = reason
        super().__init__(f"{controller}: parameter {param!r}: {reason}")


class WrongDevice(RocomaError, RuntimeError):
    """The device at a drive's node id is not the one its config (or its EDS/DCF) names:
    its identity object (0x1018) differs. Bring-up refuses it before writing anything."""


class SimulatorFailed(RocomaError, RuntimeError):
    """The demo's simulated drives in a process of their own failed: the process could not
    start, died, or reported a drive's failure (the message says which, with its last
    words)."""
