"""rocoma_can/fleet/config.py (the ``zenoh:`` section), rocoma_can/fleet/bridge.py
(open_session): a bad section lists every problem, ``run --zenoh`` refuses a wildcard prefix,
and a Zenoh config file that cannot be read is one line naming it."""
from __future__ import annotations

import pytest

from rocoma_can.cli.demo.config import demo_config
from rocoma_can.cli.main import main
from rocoma_can.errors import ConfigError
from rocoma_can.fleet.bridge import FleetError, open_session
from rocoma_can.runtime.config import validate

RATE = 100.0


def test_a_bad_zenoh_section_lists_every_problem(virtual_channel):
    cfg = demo_config(virtual_channel, drives=2, rate=RATE)
    cfg["zenoh"] = {"prefix": "rocoma/*", "mode": "router", "listen": "7447",
                    "allow_commands": "yes", "drives_period": 0, "colour": 1,
                    "deadman": "ops//console", "required": False}
    with pytest.raises(ConfigError) as err:
        validate(cfg)
    text = "\n".join(err.value.problems)
    for key in ("zenoh.prefix: 'rocoma/*' is not a concrete key expression", "zenoh.mode",
                "zenoh.listen", "zenoh.allow_commands", "zenoh.drives_period",
                "zenoh.colour: unknown key", "zenoh.deadman: 'ops//console'"):
        assert key in text, text
    cfg["zenoh"] = {"prefix": "rocoma/r1/", "deadman": "ops/console1", "required": False}
    with pytest.raises(ConfigError) as err:
        validate(cfg)
    text = "\n".join(err.value.problems)
    assert "zenoh.prefix: 'rocoma/r1/'" in text and "zenoh.deadman: needs zenoh.required" in text


def test_run_refuses_a_wildcard_prefix_on_the_command_line(tmp_path, virtual_channel, capsys):
    """A prefix with a wildcard would answer, and act on, other managers' queries."""
    import yaml
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(demo_config(virtual_channel, drives=2, rate=RATE)))
    assert main(["run", str(path), "--zenoh", "rocoma/*", "--duration", "0.1"]) == 2
    assert "--zenoh.prefix: 'rocoma/*' is not a concrete key expression" in \
        capsys.readouterr().err


@pytest.mark.parametrize("content, said", [
    (b"mode: peer\n  connect: x\n", "line 2, column 10: not valid YAML: mapping values are "
                                     "not allowed here"),
    (b"mode: \xff\n", "not UTF-8 text"),
])
def test_a_zenoh_config_file_that_cannot_be_read_is_one_line_naming_it(tmp_path, content,
                                                                       said):
    """zenoh.config_file is a config too: its error names the file and the line, on one
    line (PyYAML said ``<unicode string>`` over four lines)."""
    path = tmp_path / "zenoh.yaml"
    path.write_bytes(content)
    with pytest.raises(FleetError) as refused:
        open_session(None, [], [], None, str(path))
    message = str(refused.value)
    assert f"{path}: {said}" in message and "\n" not in message, message
    assert "<unicode string>" not in message
