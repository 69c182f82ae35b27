"""Controllers loaded by name from configuration (rocoma's pluginlib plugins).

A controller is named either by an entry point in the ``rocoma_can.controllers`` group (a
distribution declares ``pd = "my_pkg.pd:PD"`` under
``[project.entry-points."rocoma_can.controllers"]``)
or directly as ``"package.module:Class"``. It is built as ``cls(name, **params)``.

Configuration (YAML), emergency controllers shared by name::

    controllers:
      - name: pd
        plugin: pd                  # entry point name, or "my_pkg.my_mod:MyController"
        params: {kp: 100.0, kd: 2.0}
        emergency: damp             # optional: an entry of emergency_controllers
      - name: legs_and_arm          # a ControllerTuple: members run in this order
        tuple:
          - {name: legs, plugin: pd, params: {joints: [hip, knee]}}
          - {name: arm, plugin: hold}
    emergency_controllers:
      - name: damp
        plugin: damp
        params: {gain: 5.0}

Every mistake raises PluginError naming the place in the configuration, e.g.
``controllers[2].plugin: no controller plugin named 'pdd' (known: damp, hold, pd)``.
Everything is built before anything is added to a manager, so a bad file changes nothing.
"""
from __future__ import annotations

import importlib
import inspect
import logging
import numbers
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from typing import Any

from .errors import ParamError, PluginError
from .interfaces import Controller, EmergencyController, FailproofController
from .spelling import did_you_mean
from .tuples import ControllerTuple, EmergencyControllerTuple

log = logging.getLogger(__name__)

GROUP = "rocoma_can.controllers"

_ENTRY_KEYS = frozenset({"name", "plugin", "params", "tuple"})
_LAYERS = (FailproofController, EmergencyController, Controller)  # most specific first


@dataclass(frozen=True)
class LoadedController:
    """A controller built from one ``controllers`` entry, with its emergency partner."""
    controller: Controller
    emergency: EmergencyController | None
    where: str


def available_plugins() -> dict[str, EntryPoint]:
    """The installed controller entry points by name (the first wins on duplicates)."""
    found: dict[str, EntryPoint] = {}
    for ep in entry_points(group=GROUP):
        found.setdefault(ep.name, ep)
    return found


def load_controller_class(spec: str, where: str = "") -> type:
    """The controller class an entry point name or ``"package.module:Class"`` names."""
    if not isinstance(spec, str) or not spec.strip():
        raise _error(where, "expected an entry point name or 'package.module:Class', "
                            f"got {spec!r}")
    cls = _import_class(spec, where) if ":" in spec else _entry_point_class(spec, where)
    if not (inspect.isclass(cls) and issubclass(cls, (Controller, FailproofController))):
        raise _error(where, f"{spec!r} is not a Controller subclass (got {cls!r})")
    if inspect.isabstract(cls):
        missing = ", ".join(sorted(getattr(cls, "__abstractmethods__", ())))
        raise _error(where, f"{spec!r} is abstract: it does not implement {missing}")
    return cls


def create_controller(spec: str, name: str, params: Mapping[str, Any] | None,
                      where: str = "") -> Controller | EmergencyController | FailproofController:
    """Load the class ``spec`` names and build it as ``cls(name, **params)``.

    ``where`` is the entry's path; errors point at its ``.plugin`` or ``.params``.
    """
    cls = load_controller_class(spec, _at(where, "plugin"))
    return _instantiate(cls, name, params, where)


def load_emergency_controllers(entries: Sequence[Mapping[str, Any]] | None,
                               where: str = "emergency_controllers"
                               ) -> dict[str, EmergencyController]:
    """Build the emergency controllers of a config list, by name."""
    built = _build_list(entries, where, EmergencyController)
    return {controller.name: controller for controller, _, _ in built}


def load_controllers(entries: Sequence[Mapping[str, Any]] | None, where: str = "controllers",
                     emergency_controllers: Mapping[str, EmergencyController] | None = None
                     ) -> list[LoadedController]:
    """Build the switchable controllers of a config list, paired with their emergency
    controllers (looked up by name in ``emergency_controllers``)."""
    emergency_controllers = emergency_controllers or {}
    loaded = []
    for controller, entry, at in _build_list(entries, where, Controller,
                                             exclude=EmergencyController,
                                             extra_keys=frozenset({"emergency"})):
        loaded.append(LoadedController(
            controller, _emergency_of(entry, at, emergency_controllers), at))
    return loaded


def load_config(config: Mapping[str, Any], where: str = "", *,
                note_unused: bool = True) -> list[LoadedController]:
    """Build ``emergency_controllers`` then ``controllers`` of a config mapping (other keys
    belong to other parts of the configuration and are ignored here). ``note_unused``: log
    (INFO) the emergency controllers no controller uses; a caller that reports them itself
    (``unused_emergency``) passes False, so the note is not said once per build."""
    if not isinstance(config, Mapping):
        raise _error(where, f"expected a mapping with 'controllers' and "
                            f"'emergency_controllers', got {_kind(config)}")
    emergency_where = _at(where, "emergency_controllers")
    emergency = load_emergency_controllers(config.get("emergency_controllers"),
                                           emergency_where)
    controllers_where = _at(where, "controllers")
    entries = config.get("controllers")
    listed: Sequence[Any] = entries if entries is not None and _is_list(entries) else ()
    for i, entry in enumerate(listed):
        name = entry.get("name") if isinstance(entry, Mapping) else None
        if isinstance(name, str) and name in emergency:
            raise _error(f"{controllers_where}[{i}].name",
                         f"{name!r} is already the name of an emergency controller "
                         f"(in {emergency_where}); names must be unique")
    loaded = load_controllers(entries, controllers_where, emergency)
    if note_unused:
        for note in unused_emergency(loaded, emergency, where):
            log.info("%s", note)
    return loaded


def unused_emergency(loaded: Sequence[LoadedController],
                     emergency: Mapping[str, EmergencyController] | Sequence[str],
                     where: str = "") -> list[str]:
    """A note per emergency controller (or name of one) that no loaded controller uses.

    Not a warning: a config may declare one for later, and the manager runs as configured
    (a fault in a controller without an emergency controller goes to failproof)."""
    used = {item.emergency.name for item in loaded if item.emergency is not None}
    return [f"{_at(where, 'emergency_controllers')}: emergency controller {name!r} is not "
            "used by any controller" for name in emergency if name not in used]


def add_to_manager(manager: Any, config: Mapping[str, Any], where: str = "", *,
                   note_unused: bool = True) -> list[LoadedController]:
    """Build every controller of ``config``, then add them to ``manager`` with their
    emergency controllers. Nothing is added when any entry is bad."""
    loaded = load_config(config, where, note_unused=note_unused)
    for item in loaded:
        manager.add_controller(item.controller, emergency=item.emergency)
    return loaded


# -- building entries -------------------------------------------------------------------------

def _build_list(entries: Any, where: str, base: type, exclude: type | None = None,
                extra_keys: frozenset[str] = frozenset()
                ) -> list[tuple[Any, Mapping[str, Any], str]]:
    """(controller, entry, path) for each entry of a config list; names must be unique."""
    if entries is None:
        return []
    if not _is_list(entries):
        raise _error(where, f"expected a list of controller entries, got {_kind(entries)}")
    built = []
    first_at: dict[str, str] = {}
    for i, entry in enumerate(entries):
        at = f"{where}[{i}]"
        controller = _build(entry, at, base, exclude, extra_keys)
        if controller.name in first_at:
            raise _error(_at(at, "name"), f"duplicate name {controller.name!r} "
                                          f"(first used at {first_at[controller.name]})")
        first_at[controller.name] = at
        built.append((controller, entry, at))
    return built


def _build(entry: Any, where: str, base: type, exclude: type | None,
           extra_keys: frozenset[str]) -> Any:
    if not isinstance(entry, Mapping):
        raise _error(where, f"expected a mapping with 'name' and 'plugin' (or 'tuple'), "
                            f"got {_kind(entry)}")
    allowed = _ENTRY_KEYS | extra_keys
    for key in entry:
        if key not in allowed:
            raise _error(_at(where, str(key)), "unknown key" + did_you_mean(str(key), allowed)
                         + f" (allowed: {', '.join(sorted(allowed))})")
    name = entry.get("name")
    if not isinstance(name, str) or not name:
        raise _error(_at(where, "name"), f"expected a non-empty string, got {name!r}")
    if ("plugin" in entry) == ("tuple" in entry):
        raise _error(where, f"entry {name!r} needs exactly one of 'plugin' or 'tuple'")
    if "tuple" in entry:
        return _build_tuple(entry, name, where, base)
    spec = entry["plugin"]
    plugin_at = _at(where, "plugin")
    cls = load_controller_class(spec, plugin_at)
    layer = next(t for t in _LAYERS if issubclass(cls, t))
    if not issubclass(cls, base) or (exclude is not None and issubclass(cls, exclude)):
        hint = "; declare it under emergency_controllers" if layer is EmergencyController else ""
        raise _error(plugin_at, f"{spec!r} is a{_an(layer)} {layer.__name__}, but this entry "
                                f"needs a{_an(base)} {base.__name__}{hint}")
    return _instantiate(cls, name, entry.get("params"), where)


def _build_tuple(entry: Mapping[str, Any], name: str, where: str, base: type) -> ControllerTuple:
    if "params" in entry:
        raise _error(_at(where, "params"), "a tuple takes no params; give them to its members")
    members_at = _at(where, "tuple")
    members = entry["tuple"]
    if not _is_list(members) or not members:
        raise _error(members_at, f"expected a non-empty list of member entries, "
                                 f"got {_kind(members)}")
    tuple_cls = EmergencyControllerTuple if issubclass(base, EmergencyController) \
        else ControllerTuple
    built = _build_list(members, members_at, tuple_cls.MEMBER_TYPE)
    return tuple_cls(name, [controller for controller, _, _ in built])


def _instantiate(cls: type, name: str, params: Any,
                 where: str) -> Controller | EmergencyController | FailproofController:
    params_at = _at(where, "params")
    if params is None:
        params = {}
    if not isinstance(params, Mapping) or not all(isinstance(k, str) for k in params):
        raise _error(params_at, f"expected a mapping of keyword arguments for "
                                f"{cls.__name__}, got {_kind(params)}")
    try:
        signature = inspect.signature(cls)
    except (TypeError, ValueError):  # no introspectable signature: let the call decide
        signature = None
    if signature is not None:
        accepted = ", ".join(list(signature.parameters)[1:]) or "no parameters"
        takes_any = any(p.kind is p.VAR_KEYWORD for p in signature.parameters.values())
        for key in params:
            if not takes_any and key not in signature.parameters:
                raise _error(_at(params_at, key), f"{cls.__name__} has no parameter {key!r}"
                             f"{did_you_mean(key, list(signature.parameters)[1:])} "
                             f"(accepts: {accepted})")
        try:
            signature.bind(name, **params)
        except TypeError as exc:
            raise _error(params_at, f"{cls.__name__}() {exc} (accepts: {accepted})") from None
    # A value its annotation rules out would fail inside the constructor with a message
    # about an operator, not about the parameter: said here, with its path.
    mismatch = annotated_mismatch(cls, params)
    if mismatch is not None:
        raise _error(_at(params_at, mismatch.param), mismatch.reason)
    try:
        controller: Controller | EmergencyController | FailproofController = cls(name, **params)
    except ParamError as exc:  # the library's parameter checks: the parameter is the path
        raise _error(_at(params_at, exc.param), exc.reason) from exc
    except Exception as exc:
        raise _error(params_at, f"{cls.__name__}({name!r}, **params) failed: {exc}") from exc
    # The config's name is the one the manager and the other entries refer to.
    controller.name = name
    return controller


def _emergency_of(entry: Mapping[str, Any], where: str,
                  emergency: Mapping[str, EmergencyController]) -> EmergencyController | None:
    ref = entry.get("emergency")
    if ref is None:
        return None
    at = _at(where, "emergency")
    if not isinstance(ref, str):
        raise _error(at, f"expected the name of an emergency controller, got {ref!r}")
    if ref not in emergency:
        declared = ", ".join(sorted(emergency)) or "none"
        raise _error(at, f"no emergency controller named {ref!r}"
                         f"{did_you_mean(ref, emergency)} (declared: {declared})")
    return emergency[ref]


# -- finding classes --------------------------------------------------------------------------

def _entry_point_class(spec: str, where: str) -> Any:
    plugins = available_plugins()
    ep = plugins.get(spec)
    if ep is None:
        known = ", ".join(sorted(plugins)) or f"none installed in group {GROUP!r}"
        hint = " (a class is named as 'package.module:Class')" if "." in spec else ""
        raise _error(where, f"no controller plugin named {spec!r}"
                            f"{did_you_mean(spec, plugins)} (known: {known}){hint}")
    try:
        return ep.load()
    except Exception as exc:
        raise _error(where, f"controller plugin {spec!r} ({ep.value}) failed to load: "
                            f"{type(exc).__name__}: {exc}") from exc


def _import_class(spec: str, where: str) -> Any:
    module_name, _, qualname = spec.partition(":")
    if not module_name or not qualname:
        raise _error(where, f"expected 'package.module:Class', got {spec!r}")
    try:
        obj = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        raise _error(where, f"cannot import module {module_name!r}: {exc}") from exc
    except Exception as exc:
        raise _error(where, f"importing module {module_name!r} raised "
                            f"{type(exc).__name__}: {exc}") from exc
    for part in qualname.split("."):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            raise _error(where, f"module {module_name!r} has no class {qualname!r}") from None
    return obj


# -- messages ---------------------------------------------------------------------------------

def _at(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _error(where: str, detail: str) -> PluginError:
    return PluginError(f"{where}: {detail}" if where else detail)


def _kind(value: Any) -> str:
    return f"{type(value).__name__} {value!r}"


def _an(cls: type) -> str:
    return "n" if cls.__name__[0] in "AEIOU" else ""


def _is_list(value: Any) -> bool:
    return isinstance(value, Sequence) and not isinstance(value, (str, bytes))


#: what an annotated parameter must be: the YAML scalars a constructor can be given (and
#: numpy's numbers, from a caller in Python)
_KINDS: dict[Any, tuple[str, Callable[[Any], bool]]] = {
    float: ("a number (float)", lambda v: isinstance(v, numbers.Real) and not isinstance(v, bool)),
    int: ("an integer (int)",
          lambda v: isinstance(v, numbers.Integral) and not isinstance(v, bool)),
    bool: ("true or false (bool)", lambda v: isinstance(v, bool)),
    str: ("a string (str)", lambda v: isinstance(v, str)),
}


def annotated_mismatch(cls: type, params: Mapping[str, Any]) -> ParamError | None:
    """The first of ``params`` whose value is not what ``cls.__init__`` annotates it as
    (float, int, bool, str, optionally ``| None``), or None.

    A controller written as ``def __init__(self, name, kp: float = 20.0)`` that compares
    ``kp < 0`` fails on ``kp: high`` with "'<' not supported between instances of 'str' and
    'int'", which names neither the parameter nor what it should be; its annotation says
    both. Parameters annotated otherwise (``Any``, lists, classes) are the constructor's to
    check, as this library's controllers do with the helpers below.
    """
    try:
        hints = typing.get_type_hints(cls.__init__)  # type: ignore[misc]  # the class's own
    except Exception:  # noqa: BLE001 - unresolvable annotations: nothing to check against
        return None
    for param, value in params.items():
        hint = hints.get(param)
        optional = False
        if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
            members = [a for a in typing.get_args(hint) if a is not type(None)]
            optional = len(members) < len(typing.get_args(hint))
            hint = members[0] if len(members) == 1 else None
        if hint not in _KINDS or (value is None and optional):
            continue
        kind, fits = _KINDS[hint]
        if not fits(value):
            none = " or null" if optional else ""
            return ParamError(cls.__name__, param, f"expected {kind}{none}, got {value!r}")
    return None
