"""rocoma_can/runtime/config.py, config_check.py: run-time config: every problem reported with its
YAML path (the buses and their load: test_bus_load.py)."""
from __future__ import annotations

import copy
import logging

import pytest
import yaml
from fixtures.configs import good
from fixtures.paths import ROOT

from rocoma_can import TimingSupervision
from rocoma_can.drivers.hardware import CanopenHardware
from rocoma_can.drivers.plan.config import Supervision
from rocoma_can.runtime.config import ConfigError, load, load_reach, validate

EXAMPLES = ROOT / "rocoma_can" / "examples"


def test_good_config_builds():
    config = validate(good())
    assert config.rate == 100 and config.dt == pytest.approx(0.01)
    assert [d.name for d in config.drives] == ["j1", "j2"]
    assert config.manager.estop_cob_id == 0x0A0 and config.manager.estop_must_be_cleared


@pytest.mark.parametrize("shipped", sorted(p.name for p in EXAMPLES.glob("*.yaml")))
def test_shipped_examples_are_valid(shipped):
    assert load(EXAMPLES / shipped).drives


def _set(path: str, value):
    def edit(cfg: dict) -> None:
        *parents, last = path.split(".")
        node = cfg
        for key in parents:
            node = node[int(key)] if key.isdigit() else node.setdefault(key, {})
        if value is _DELETE:
            del node[last]
        elif last.isdigit():
            node[int(last)] = value
        else:
            node[last] = value
    return edit


_DELETE = object()

BAD = [
    ("rate", _set("rate", 0), "rate: expected a loop rate"),
    ("rate type", _set("rate", "fast"), "rate: expected a loop rate"),
    ("unknown top key", _set("rates", 5), "rates: unknown key, did you mean 'rate'?"),
    ("bitrate", _set("bus.bitrate", 2_000_000), "bus.bitrate: expected an integer"),
    ("bus key", _set("bus.chanel", "x"), "bus.chanel: unknown key, did you mean 'channel'?"),
    ("node id", _set("manager.node_id", 200), "manager.node_id: expected an integer 1..127"),
    ("estop cob", _set("manager.estop_cob_id", 0x601), "manager.estop_cob_id: 0x601 is reserved"),
    ("estop cob range", _set("manager.estop_cob_id", 0x1000), "manager.estop_cob_id: expected"),
    ("must clear", _set("manager.estop_must_be_cleared", "yes"),
     "manager.estop_must_be_cleared: expected true or false"),
    ("clients", _set("manager.switch_clients", [5]), "manager.switch_clients: not supported"),
    ("priority", _set("realtime.priority", 120), "realtime.priority"),
    ("spin past a period", _set("realtime.spin_us", 10_000),
     "realtime.spin_us: expected null or µs, 0 <= spin_us < one period (10000.0 µs at the rate)"),
    ("spin type", _set("realtime.spin_us", "fast"), "realtime.spin_us: expected null or µs"),
    ("spin bool", _set("realtime.spin_us", True), "realtime.spin_us: expected null or µs"),
    ("spin negative", _set("realtime.spin_us", -1), "realtime.spin_us: expected null or µs"),
    ("tpdo cycles", _set("supervision", {"tpdo_timeout_cycles": 0.5}),
     "supervision.tpdo_timeout_cycles: expected an integer 1..10000"),
    ("sdo timeout", _set("supervision", {"sdo_timeout": 0}),
     "supervision.sdo_timeout: expected a number 0.01..30.0"),
    ("supervision key", _set("supervision", {"tpdo_cycles": 5}),
     "supervision.tpdo_cycles: unknown key, did you mean 'tpdo_timeout_cycles'?"),
    ("no drives", _set("drives", []), "drives: expected a non-empty list"),
    ("drive field", _set("drives.1.node_id", 0), "drives[1]: drive 'j2': node_id must be"),
    ("drive key", _set("drives.0.gear", 2),
     "drives[0].gear: unknown key, did you mean 'gear_ratio'? (known: accept_unsupervised, "),
    ("drive mode key", _set("drives.0.mode", ["csp"]),
     "drives[0].mode: unknown key, did you mean 'modes'? (known: "),
    ("zenoh key", _set("zenoh", {"prefx": "rocoma/x"}),
     "zenoh.prefx: unknown key, did you mean 'prefix'? (known: "),
    ("param type", _set("controllers.0.params", {"kp": "high"}),
     "controllers[0].params.kp: expected a number, got 'high'"),
    ("param range", _set("controllers.0.params", {"kd": -1}),
     "controllers[0].params.kd: must be >= 0.0, got -1.0"),
    ("param key", _set("controllers.0.params", {"kpp": 5}),
     "controllers[0].params.kpp: JointPD has no parameter 'kpp', did you mean 'kp'? (accepts: "),
    ("drive mode", _set("drives.0.modes", ["vl"]), "drives[0]: drive 'j1': modes: unknown mode"),
    ("same node", _set("drives.1.node_id", 1), "drives[1].node_id: 1 is already used by drives[0]"),
    ("same name", _set("drives.1.name", "j1"), "drives[1].name: 'j1' is already drives[0]"),
    ("manager node", _set("drives.1.node_id", 100), "drives[1].node_id: 100 is the manager's"),
    ("no controllers", _set("controllers", []), "controllers: at least one controller"),
    ("plugin", _set("controllers.0.plugin", "pdd"), "controllers[0].plugin: no controller plugin"),
    ("emergency", _set("controllers.0.emergency", "dmap"),
     "controllers[0].emergency: no emergency"),
]


def test_supervision_margins_reach_the_hardware():
    cfg = good()
    cfg["bus"] = {"interface": "virtual", "channel": "config-supervision"}
    cfg["supervision"] = {"tpdo_timeout_cycles": 25, "heartbeat_timeout_factor": 5.0,
                          "consumer_factor": 3, "sdo_timeout": 2.0}
    config = validate(cfg)
    assert config.supervision == Supervision(tpdo_timeout_cycles=25, heartbeat_timeout_factor=5.0,
                                             consumer_factor=3, sdo_timeout=2.0)
    hw = CanopenHardware(config.bus, config.drives, config.manager.node_id, config.dt,
                         supervision=config.supervision)
    try:
        assert hw.supervisor.tpdo_timeout_cycles == 25
        assert hw.consumer_ms == 3 * 100  # consumer_factor x the manager's heartbeat
    finally:
        hw.close()
    assert validate(good()).supervision == Supervision()  # nothing given: the defaults


def test_timing_budgets_come_from_the_yaml():
    cfg = good()
    cfg["timing"] = {"advance": 0.8, "hang": 40}
    assert validate(cfg).timing == TimingSupervision(advance=0.8, hang=40)
    assert validate(good()).timing == TimingSupervision()


@pytest.mark.parametrize("label, edit, expected", BAD, ids=[b[0] for b in BAD])
def test_each_problem_names_its_path(label, edit, expected):
    cfg = copy.deepcopy(good())
    edit(cfg)
    with pytest.raises(ConfigError) as info:
        validate(cfg, source="robot.yaml")
    assert any(p.startswith("robot.yaml: " + expected) for p in info.value.problems), \
        info.value.problems


def test_all_problems_are_collected():
    cfg = good()
    cfg["rate"] = -1
    cfg["manager"]["node_id"] = 0
    cfg["drives"][1]["node_id"] = 1
    cfg["controllers"][0]["plugin"] = "nope"
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    paths = [p.split(": ")[1] for p in info.value.problems]
    assert paths == ["rate", "manager.node_id", "drives[1].node_id", "controllers[0].plugin"]


ONE_MISTAKE = [
    ("same name", _set("drives.1.name", "j1"), ["drives[1].name: 'j1' is already drives[0]"]),
    ("same node", _set("drives.1.node_id", 1),
     ["drives[1].node_id: 1 is already used by drives[0]"]),
    ("manager's node", _set("drives.1.node_id", 100),
     ["drives[1].node_id: 100 is the manager's node id (manager.node_id)"]),
    ("misspelt controllers", lambda cfg: cfg.update(controlers=cfg.pop("controllers")),
     ["controlers: unknown key, did you mean 'controllers'? (known: bus, buses, controllers, "
      "drives, emergency_controllers, manager, rate, realtime, ros2, supervision, timing, "
      "urdf, zenoh)"]),
    ("misspelt emergency", lambda cfg: cfg.update(
        emergency_controler=cfg.pop("emergency_controllers")),
     ["emergency_controler: unknown key, did you mean 'emergency_controllers'? (known: bus, "
      "buses, controllers, drives, emergency_controllers, manager, rate, realtime, ros2, "
      "supervision, timing, urdf, zenoh)"]),
    ("misspelt drives", lambda cfg: cfg.update(drive=cfg.pop("drives")),
     ["drive: unknown key, did you mean 'drives'? (known: bus, buses, controllers, drives, "
      "emergency_controllers, manager, rate, realtime, ros2, supervision, timing, urdf, "
      "zenoh)"]),
    ("misspelt node_id", lambda cfg: cfg["drives"][1].update(
        node_ids=cfg["drives"][1].pop("node_id")),
     ["drives[1].node_ids: unknown key, did you mean 'node_id'? (known: accept_unsupervised, "
      "axis, bus, eds, feedback, gear_ratio, guarding, heartbeat_ms, homing_method, "
      "homing_timeout, identity, "
      "increments_per_rev, limits, max_torque_nm, max_velocity, modes, name, node_id, "
      "pdo_bytes, position_max, position_min, rated_torque_nm)"]),
    ("a failed drive is still named", lambda cfg: (
        cfg["drives"][1].update(node_id=0), cfg["manager"].update(required_drives=["j2"])),
     ["drives[1]: drive 'j2': node_id must be an integer 1..127, got 0"]),
]


@pytest.mark.parametrize("label, edit, expected", ONE_MISTAKE, ids=[m[0] for m in ONE_MISTAKE])
def test_one_mistake_is_one_problem(label, edit, expected):
    """Not also its follow-ups: a taken drive name or node id is not also its PDOs' COB-ID
    clashes, a misspelt section is not also the section missing."""
    cfg = copy.deepcopy(good())
    edit(cfg)
    with pytest.raises(ConfigError) as info:
        validate(cfg, source="robot.yaml")
    assert info.value.problems == [f"robot.yaml: {p}" for p in expected]


def test_a_valid_config_warns_about_nothing(caplog):
    """An emergency controller no controller uses is a note of the config (check-config
    prints it), not a WARNING, and not logged by the check."""
    cfg = good()
    cfg["controllers"][0].pop("emergency")
    with caplog.at_level(logging.DEBUG, logger="rocoma_can"):
        config = validate(cfg)
    assert config.notes == ["emergency_controllers: emergency controller 'damp' is not used "
                            "by any controller"]
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.INFO] == []
    assert validate(good()).notes == []


def test_yaml_file_errors(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("rate: [1,\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load(bad)
    ok = tmp_path / "ok.yaml"
    ok.write_text(yaml.safe_dump(good()))
    assert load(ok).source == str(ok)


def test_a_consumer_time_the_drives_cannot_hold_is_a_config_problem():
    """check-config said yes and run refused: heartbeat_ms x consumer_factor is written to
    each drive's 0x1016 as 16-bit milliseconds."""
    cfg = good()
    cfg["manager"]["heartbeat_ms"] = 1000
    cfg["supervision"] = {"consumer_factor": 90.0}
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    assert any("supervision.consumer_factor: 90 x manager.heartbeat_ms 1000 = 90000 ms" in p
               for p in info.value.problems), info.value.problems


@pytest.mark.parametrize("text, expected", [
    ("- bus: {channel: can0}\n- rate: 100\n", "(top): expected a mapping"),   # a YAML list
    ("", "(top): expected a mapping"),                                        # empty
    ("just words\n", "(top): expected a mapping"),                            # a scalar
    ("rate: 100\ndrives: [1,\n", "line 3"),                  # a list never closed
    ("rate: 100\n  bus: x\n", "line 2"),                     # indentation
    ("rate: 100\nbus: {channel: \"can0}\n", "line 2"),       # a string never closed
    ("rate: 100\nbus: \x07\n", "not valid YAML"),             # a control character
    ("rate: 100\n\trate: 200\n", "line 2"),                   # a tab where YAML wants spaces
])
def test_every_config_error_names_the_file(tmp_path, text, expected):
    """Through load(), as check-config and run read a config: each problem begins with the
    file's name (never ``<unicode string>`` or a bare ``(top)``), a YAML syntax error with
    the line YAML found it on."""
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as refused:
        load(path)
    for problem in refused.value.problems:
        assert problem.startswith(f"{path}: "), problem
        assert "<unicode string>" not in problem and "\n" not in problem, problem
    assert expected in str(refused.value), refused.value.problems


@pytest.mark.parametrize("text, said", [
    ("rate: 100\ndrives: [1,\n", "line 3, column 1: not valid YAML: expected the node "
     "content, but found '<stream end>' (while parsing a flow node)"),
    ('rate: 100\nbus: {channel: "can0}\n', "line 3, column 1: not valid YAML: found "
     "unexpected end of stream (while scanning a quoted scalar that began at line 2, column "
     "16)"),
])
def test_a_yaml_syntax_error_says_line_and_column_once(tmp_path, text, said):
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as refused:
        load(path)
    assert refused.value.problems == [f"{path}: {said}"]


def test_a_config_that_is_not_a_mapping_says_what_it_is(tmp_path):
    for text, what in (("- a\n- b\n", "a list"), ("", "an empty file"),
                       ("42\n", "an integer")):
        path = tmp_path / "robot.yaml"
        path.write_text(text)
        with pytest.raises(ConfigError) as refused:
            load(path)
        assert refused.value.problems == [
            f"{path}: (top): expected a mapping with bus, rate, drives, controllers, got "
            f"{what}"]
        with pytest.raises(ConfigError) as refused:  # -c CONFIG of the operator verbs
            load_reach(path)                          # ("got NoneType" for an empty file)
        assert refused.value.problems == [
            f"{path}: (top): expected a mapping with bus and manager, got {what}"]
