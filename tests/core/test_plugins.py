"""rocoma_can/plugins.py: plugin loading: entry points, "module:Class" specs, config lists, and
their error paths."""
from __future__ import annotations

import copy
import logging

import pytest
from fixtures import plugin_samples
from fixtures.plugin_samples import Brake, Gains

from rocoma_can.controllers.torque_off import TorqueOff
from rocoma_can.drivers.protocol.joints import JointCommand, JointState
from rocoma_can.plugins import (
    GROUP,
    LoadedController,
    PluginError,
    add_to_manager,
    available_plugins,
    create_controller,
    load_config,
    load_controller_class,
    load_controllers,
    load_emergency_controllers,
)
from rocoma_can.tuples import ControllerTuple, EmergencyControllerTuple

CONFIG = {
    "controllers": [
        {"name": "pd", "plugin": "fixtures.plugin_samples:Gains", "params": {"kp": 100.0, "kd": 2.0},
         "emergency": "brake"},
        {"name": "soft", "plugin": "fixtures.plugin_samples:Gains", "params": {"kp": 5.0},
         "emergency": "brake"},
        {"name": "legs_and_arm", "tuple": [
            {"name": "legs", "plugin": "fixtures.plugin_samples:Gains", "params": {"kp": 1.0}},
            {"name": "arm", "plugin": "fixtures.plugin_samples:Outer.Inner", "params": {"kp": 2.0}},
        ]},
    ],
    "emergency_controllers": [
        {"name": "brake", "plugin": "fixtures.plugin_samples:Brake", "params": {"gain": 5.0}},
    ],
    "bus": {"channel": "can0"},  # another part's section: ignored here
}


def test_entry_point_lookup():
    assert "torque_off" in available_plugins()
    assert load_controller_class("torque_off") is TorqueOff
    ctrl = create_controller("torque_off", "off", None)
    assert isinstance(ctrl, TorqueOff) and ctrl.name == "off"


def test_module_class_lookup_and_params():
    assert load_controller_class("fixtures.plugin_samples:Gains") is Gains
    assert load_controller_class("fixtures.plugin_samples:Outer.Inner") is plugin_samples.Outer.Inner
    ctrl = create_controller("fixtures.plugin_samples:Gains", "pd", {"kp": 3.0})
    assert (ctrl.name, ctrl.kp, ctrl.kd) == ("pd", 3.0, 1.0)


def test_the_config_name_wins_over_the_constructor():
    assert create_controller("fixtures.plugin_samples:Renamed", "mine", None).name == "mine"


def test_load_config_builds_layers_pairs_and_tuples():
    loaded = load_config(CONFIG)
    assert [item.controller.name for item in loaded] == ["pd", "soft", "legs_and_arm"]
    assert [item.where for item in loaded] == ["controllers[0]", "controllers[1]",
                                               "controllers[2]"]
    pd, soft, combo = loaded
    assert isinstance(pd.emergency, Brake) and pd.emergency.gain == 5.0
    assert soft.emergency is pd.emergency  # shared by name
    assert combo.emergency is None
    assert isinstance(combo.controller, ControllerTuple)
    assert [(m.name, m.kp) for m in combo.controller.controllers] == [("legs", 1.0),
                                                                      ("arm", 2.0)]


def test_emergency_tuple_and_lists_on_their_own():
    emergency = load_emergency_controllers([
        {"name": "both", "tuple": [{"name": "a", "plugin": "fixtures.plugin_samples:Brake"},
                                   {"name": "b", "plugin": "fixtures.plugin_samples:Brake"}]}])
    assert isinstance(emergency["both"], EmergencyControllerTuple)
    loaded = load_controllers([{"name": "x", "plugin": "fixtures.plugin_samples:Gains",
                                "params": {"kp": 1.0}, "emergency": "both"}],
                              emergency_controllers=emergency)
    assert loaded == [LoadedController(loaded[0].controller, emergency["both"],
                                       "controllers[0]")]
    assert load_controllers(None) == [] and load_emergency_controllers(None) == {}


def test_unused_emergency_controller_is_a_note_not_a_warning(caplog):
    """A valid config warns about nothing: the unused emergency controller is said once,
    at INFO, and not at all by a caller that reports it itself."""
    config = {"emergency_controllers": [{"name": "idle", "plugin": "fixtures.plugin_samples:Brake"}]}
    with caplog.at_level(logging.DEBUG, logger="rocoma_can.plugins"):
        assert load_config(config) == []
        assert load_config(config, note_unused=False) == []
    assert [(r.levelno, r.getMessage()) for r in caplog.records] == [
        (logging.INFO, "emergency_controllers: emergency controller 'idle' is not used by any "
                       "controller")]


def bad(config_path: str, value):
    """CONFIG with one value replaced, or deleted for KeyError (path 'controllers.2.name')."""
    config = copy.deepcopy(CONFIG)
    *parents, last = config_path.split(".")
    node = config
    for key in parents:
        node = node[int(key)] if isinstance(node, list) else node[key]
    if isinstance(node, list):
        node[int(last)] = value
    elif value is KeyError:
        del node[last]
    else:
        node[last] = value
    return config


@pytest.mark.parametrize("config, message", [
    (bad("controllers.0.plugin", "pdd"),
     "controllers[0].plugin: no controller plugin named 'pdd', did you mean 'pd'? (known: "),
    (bad("controllers.0.plugin", "plugin_samples.Gains"),
     "controllers[0].plugin: no controller plugin named 'plugin_samples.Gains'"),
    (bad("controllers.1.plugin", "fixtures.plugin_samples:Gainz"),
     "controllers[1].plugin: module 'fixtures.plugin_samples' has no class 'Gainz'"),
    (bad("controllers.1.plugin", "no_such_module:Gains"),
     "controllers[1].plugin: cannot import module 'no_such_module'"),
    (bad("controllers.1.plugin", "fixtures.plugin_samples_broken:Gains"),
     "controllers[1].plugin: importing module 'fixtures.plugin_samples_broken' raised RuntimeError"),
    (bad("controllers.1.plugin", "fixtures.plugin_samples:"),
     "controllers[1].plugin: expected 'package.module:Class', got 'fixtures.plugin_samples:'"),
    (bad("controllers.1.plugin", ""),
     "controllers[1].plugin: expected an entry point name or 'package.module:Class'"),
    (bad("controllers.1.plugin", "fixtures.plugin_samples:NotAController"),
     "controllers[1].plugin: 'fixtures.plugin_samples:NotAController' is not a Controller subclass"),
    (bad("controllers.1.plugin", "fixtures.plugin_samples:NOT_A_CLASS"),
     "controllers[1].plugin: 'fixtures.plugin_samples:NOT_A_CLASS' is not a Controller subclass"),
    (bad("controllers.1.plugin", "fixtures.plugin_samples:Unfinished"),
     "controllers[1].plugin: 'fixtures.plugin_samples:Unfinished' is abstract: it does not implement "
     "advance"),
    (bad("controllers.1.plugin", "fixtures.plugin_samples:Brake"),
     "controllers[1].plugin: 'fixtures.plugin_samples:Brake' is an EmergencyController, but this entry "
     "needs a Controller; declare it under emergency_controllers"),
    (bad("controllers.1.plugin", "torque_off"),
     "controllers[1].plugin: 'torque_off' is a FailproofController"),
    (bad("emergency_controllers.0.plugin", "fixtures.plugin_samples:Gains"),
     "emergency_controllers[0].plugin: 'fixtures.plugin_samples:Gains' is a Controller, but this entry "
     "needs an EmergencyController"),
    (bad("controllers.0.params", {"kp": 1.0, "kpp": 1.0}),
     "controllers[0].params.kpp: Gains has no parameter 'kpp', did you mean 'kp'? "
     "(accepts: kp, kd)"),
    (bad("controllers.0.params", {"kp": "high"}),  # its annotation, not '>' on a str
     "controllers[0].params.kp: expected a number (float), got 'high'"),
    (bad("emergency_controllers.0.params", {"gain": [1.0]}),
     "emergency_controllers[0].params.gain: expected a number (float), got [1.0]"),
    (bad("controllers.0.params", {}),
     "controllers[0].params: Gains() missing a required argument: 'kp'"),
    (bad("controllers.0.params", {"kp": 1.0, "name": "x"}),
     "controllers[0].params: Gains() multiple values for argument 'name'"),
    (bad("controllers.0.params", {"kp": -1.0}),
     "controllers[0].params: Gains('pd', **params) failed: Gains 'pd': parameter 'kp': "
     "must be > 0"),
    (bad("controllers.0.params", [1.0]),
     "controllers[0].params: expected a mapping of keyword arguments for Gains, got list"),
    (bad("controllers.0.emergency", "brak"),
     "controllers[0].emergency: no emergency controller named 'brak', did you mean 'brake'? "
     "(declared: brake)"),
    (bad("controllers.0.emergency", 3),
     "controllers[0].emergency: expected the name of an emergency controller, got 3"),
    (bad("controllers.1.name", "pd"),
     "controllers[1].name: duplicate name 'pd' (first used at controllers[0])"),
    (bad("controllers.1.name", "brake"),
     "controllers[1].name: 'brake' is already the name of an emergency controller"),
    (bad("controllers.1.name", KeyError),
     "controllers[1].name: expected a non-empty string, got None"),
    (bad("controllers.1.parms", {}),
     "controllers[1].parms: unknown key, did you mean 'params'? (allowed: emergency, name, "
     "params, plugin, tuple)"),
    (bad("controllers.1.plugin", KeyError),
     "controllers[1]: entry 'soft' needs exactly one of 'plugin' or 'tuple'"),
    (bad("controllers.1", "pd"),
     "controllers[1]: expected a mapping with 'name' and 'plugin' (or 'tuple'), got str"),
    (bad("controllers", {"pd": {}}),
     "controllers: expected a list of controller entries, got dict"),
    (bad("controllers.2.tuple", []),
     "controllers[2].tuple: expected a non-empty list of member entries"),
    (bad("controllers.2.params", {}),
     "controllers[2].params: a tuple takes no params; give them to its members"),
    (bad("controllers.2.tuple.1.plugin", "fixtures.plugin_samples:Gainz"),
     "controllers[2].tuple[1].plugin: module 'fixtures.plugin_samples' has no class 'Gainz'"),
    (bad("controllers.2.tuple.1.name", "legs"),
     "controllers[2].tuple[1].name: duplicate name 'legs' (first used at "
     "controllers[2].tuple[0])"),
    (bad("controllers.2.tuple.0.emergency", "brake"),
     "controllers[2].tuple[0].emergency: unknown key"),
    (bad("controllers.2.tuple.1.params", {"kp": 0}),
     "controllers[2].tuple[1].params: Inner('arm', **params) failed"),
    ([1, 2], "expected a mapping with 'controllers' and 'emergency_controllers', got list"),
])
def test_every_bad_entry_names_its_path(config, message):
    with pytest.raises(PluginError) as info:
        load_config(config)
    assert str(info.value).startswith(message)
    assert isinstance(info.value, ValueError)


def test_a_plugin_that_fails_to_load_names_its_target(monkeypatch):
    # Only the lookup table is replaced: the real group has no broken entry point to load.
    from importlib.metadata import EntryPoint
    broken = EntryPoint("broken", "fixtures.plugin_samples_broken:Gains", GROUP)
    monkeypatch.setattr("rocoma_can.plugins.available_plugins", lambda: {"broken": broken})
    with pytest.raises(PluginError, match=r"^x\.plugin: controller plugin 'broken' "
                                          r"\(fixtures.plugin_samples_broken:Gains\) failed to load: "
                                          r"RuntimeError"):
        create_controller("broken", "b", None, where="x")


def test_add_to_manager_adds_pairs_or_nothing():
    manager_module = pytest.importorskip("rocoma_can.manager")
    with manager_module.ControllerManager(failproof=TorqueOff(), dt=0.01,
                                          state=JointState.zeros(2),
                                          command=JointCommand.zeros(2)) as manager:
        with pytest.raises(PluginError):
            add_to_manager(manager, bad("controllers.2.tuple.1.plugin", "nope:X"))
        assert manager.available_controllers() == []
        loaded = add_to_manager(manager, CONFIG)
        assert manager.available_controllers() == ["legs_and_arm", "pd", "soft"]
        assert manager.switch_controller("legs_and_arm") == manager_module.SwitchResult.SWITCHED
        assert manager.active_controller_name == "legs_and_arm"
        tuple_ctrl = loaded[2].controller
        assert all(m.state is tuple_ctrl.state is not None for m in tuple_ctrl.controllers)
