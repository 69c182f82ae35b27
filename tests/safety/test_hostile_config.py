"""rocoma_can/runtime/config.py: bad configuration input is a clear error, never a traceback or a
hang: YAML bombs and garbage, a bool where a whole number belongs, any file given as an EDS."""
from __future__ import annotations

import pytest

from rocoma_can.runtime.config import ConfigError, load, validate

# --- bad input is a clear error, never a traceback --------------------------------------------
BILLION_LAUGHS = "a: &a [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{chr(ord('b') + i)}: &{chr(ord('b') + i)} [{', '.join(['*' + chr(ord('a') + i)] * 10)}]\n"
    for i in range(8))


def _good_config(tmp_path, **drive) -> dict:
    return {"bus": {"interface": "virtual", "channel": "x"}, "rate": 100,
            "drives": [dict({"name": "j1", "node_id": 1, "increments_per_rev": 1 << 20,
                             "rated_torque_nm": 1.0}, **drive)]}


@pytest.mark.parametrize("case", ["alias-bomb", "self-reference", "too-big", "not-utf8",
                                  "deep-nesting"])
def test_hostile_yaml_is_refused_quickly_and_clearly(tmp_path, case):
    path = tmp_path / "robot.yaml"
    content = {"alias-bomb": BILLION_LAUGHS.encode(),
               "self-reference": b"a: &a [*a]\n",
               "too-big": b"# " + b"x" * (2 << 20) + b"\n",
               "not-utf8": b"rate: \xff\xfe\n",
               "deep-nesting": b"[" * 5000 + b"]" * 5000 + b"\n"}[case]
    path.write_bytes(content)
    with pytest.raises(ConfigError) as refused:
        load(path)
    assert all(p.startswith(f"{path}: ") for p in refused.value.problems), refused.value.problems


@pytest.mark.parametrize("key", ["node_id", "increments_per_rev", "heartbeat_ms"])
def test_a_bool_is_not_a_whole_number(tmp_path, key):
    with pytest.raises(ConfigError) as refused:
        validate(_good_config(tmp_path, **{key: True}))
    assert any(f"drives[0]: drive 'j1': {key}" in p for p in refused.value.problems), \
        refused.value.problems


@pytest.mark.parametrize("content", [b"\x00\x01\x02binary\xff" * 100, b"just some text\n",
                                     b"[1000]\nParameterName=Device type\n"],
                         ids=["binary", "not-ini", "no-pdo-objects"])
def test_every_eds_is_parsed_and_checked_at_config_time(tmp_path, content):
    eds_path = tmp_path / "vendor.eds"
    eds_path.write_bytes(content)
    with pytest.raises(ConfigError) as refused:
        validate(_good_config(tmp_path, eds=str(eds_path)), source="robot.yaml")
    problem = "\n".join(refused.value.problems)
    assert problem.startswith("robot.yaml: drives[0]: drive 'j1': ") and (
        "vendor.eds" in problem or "EDS has no" in problem), problem


@pytest.mark.parametrize("text, said", [
    ("rate: 100\nsupervision: {sdo_timeout: 0.1}\nrate: 500\n",
     "line 3, column 1: rate: given twice (first on line 1)"),
    ("drives:\n  - {name: j1, node_id: 1, node_id: 2}\n",
     "line 2, column 28: drives[0].node_id: given twice (first on line 2)"),
    ("bus: {channel: can0}\nmanager:\n  node_id: 100\n  node_id: 101\n",
     "line 4, column 3: manager.node_id: given twice (first on line 3)"),
], ids=["top", "in-a-list", "nested"])
def test_a_key_given_twice_is_refused_not_the_first_dropped(tmp_path, text, said):
    """YAML keeps the last of two equal keys and drops the first without a word: a
    `cat >> robot.yaml` of a section the file has, or two `node_id:` in a drive, ran with
    values the person did not read as the ones in force."""
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as refused:
        load(path)
    assert f"{path}: {said}: YAML keeps only the last; give it once" in \
        refused.value.problems, refused.value.problems
