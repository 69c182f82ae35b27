"""Where the live view serves (rocoma_can/live/foxglove.py): ``--foxglove HOST:PORT`` read
strictly, and every interface said whatever the spelling, as the system resolver (which
the server binds by) reads the host; the live view's options on the command line."""
from __future__ import annotations

import socket
from typing import Any, cast

import pytest

from rocoma_can.cli.foxglove_args import foxglove_from_args
from rocoma_can.cli.main import build_parser, main
from rocoma_can.live.foxglove import (
    DEFAULT_HOST,
    DEFAULT_PORT,
    FoxgloveConfig,
    FoxgloveView,
    describe_view,
    parse_address,
)

pytest.importorskip("foxglove")  # a FoxgloveView needs the SDK

EVERY = "on every interface"


def test_the_address_and_the_flag():
    assert parse_address("") == (DEFAULT_HOST, DEFAULT_PORT)
    assert parse_address("0.0.0.0:9000") == ("0.0.0.0", 9000)
    assert parse_address(":9001") == (DEFAULT_HOST, 9001)
    assert parse_address("[::1]:9002") == ("::1", 9002)
    assert parse_address("[::1]") == ("::1", DEFAULT_PORT)
    assert parse_address("::1") == ("::1", DEFAULT_PORT)
    assert parse_address("robot-1.local:0") == ("robot-1.local", 0)
    with pytest.raises(ValueError, match="port 0..65535"):
        parse_address("host:99999")
    args = build_parser().parse_args(["run", "robot.yaml", "--foxglove"])
    assert args.foxglove == (DEFAULT_HOST, DEFAULT_PORT)
    assert build_parser().parse_args(["run", "robot.yaml"]).foxglove is None


@pytest.mark.parametrize("text, wrong", [
    ("[::1", "the '[' has no ']'"),
    ("[::1]x", "after ']' comes ':PORT' or nothing"),
    ("[::1]8765", "after ']' comes ':PORT' or nothing"),
    ("[]:80", "'' in brackets is not an IPv6 address"),
    ("[127.0.0.1]:80", "'127.0.0.1' in brackets is not an IPv6 address"),
    ("::1]:80", "an IPv6 address with a port is written [IPV6]:PORT"),
    ("host:80:81", "an IPv6 address with a port is written [IPV6]:PORT"),
    ("a]:80", "'a]' is not a host name or an IPv4 address"),
    (" 127.0.0.1", "' 127.0.0.1' is not a host name or an IPv4 address"),
])
def test_a_malformed_address_is_refused_saying_what_is_wrong(text, wrong):
    """``[::1`` was served as ``::1``: what the user meant is unknown, so nothing is
    served."""
    with pytest.raises(ValueError) as caught:
        parse_address(text)
    assert str(caught.value) == (f"expected HOST:PORT, HOST, :PORT or [IPV6]:PORT, got "
                                 f"{text!r}: {wrong}")


@pytest.mark.parametrize("port", ["x", "-1", "65536", "²", "8765 "])
def test_a_port_that_is_no_port_is_refused(port):
    with pytest.raises(ValueError, match=r"^expected HOST:PORT with a port 0\.\.65535, got"):
        parse_address(f"127.0.0.1:{port}")


def _said(host: str, allow_commands: bool = False) -> str:
    """describe_view()'s line for a view on ``host`` (the server said: port 18774)."""
    view = FoxgloveView(FoxgloveConfig(host, 0, allow_commands=allow_commands),
                        manager=cast(Any, None), status=dict)
    view.served(18774, lambda message: True)
    return describe_view(view)


@pytest.mark.parametrize("text", [
    "0.0.0.0:18774", "0.0.0.0:", "0:18774", "0.0", "0x0", "000.0.0.0", "::", "::0",
    "[::]:", "[::0]:18774", "[0:0:0:0:0:0:0:0]:18779", "0:0:0:0:0:0:0:0", "::ffff:0.0.0.0",
    "[::ffff:0:0]:18774"])
def test_every_interface_is_said_however_it_is_spelt(text):
    """The server binds every interface for each of these (the system resolver reads "0"
    and "0x0" as 0.0.0.0, and a v4-mapped 0.0.0.0 takes every IPv4 interface): each is
    said, whoever reaches the machine reaches the robot."""
    host, _ = parse_address(text)
    said = _said(host)
    assert said.endswith(f"; {EVERY}: whoever reaches this machine can watch the robot and "
                         "stop it"), said
    assert f"{EVERY}: whoever reaches this machine can watch the robot and command it" in \
        _said(host, allow_commands=True)


@pytest.mark.parametrize("text", ["", ":18774", "127.0.0.1:18774", "127.1", "localhost",
                                  "[::1]:18774", "::1"])
def test_loopback_is_not_said_to_be_every_interface(text):
    host, _ = parse_address(text)
    said = _said(host)
    assert EVERY not in said, said
    assert f"ws://{f'[{host}]' if ':' in host else host}:18774 " in said


def test_a_name_that_resolves_to_every_interface_is_said(monkeypatch):
    """A host name is resolved as the server's bind resolves it: one of its addresses
    unspecified binds every interface (the name's first address is the one bound)."""
    resolve = socket.getaddrinfo
    answers = {"anywhere.example": ["127.0.0.1", "0.0.0.0"], "everywhere.example": ["::"],
               "here.example": ["127.0.0.1", "::1"]}

    def fake(host: str, *args: Any, **kwargs: Any) -> list[Any]:
        if host not in answers:
            return resolve(host, *args, **kwargs)
        return [(socket.AF_INET6 if ":" in a else socket.AF_INET, socket.SOCK_STREAM, 6, "",
                 (a, 0, 0, 0) if ":" in a else (a, 0)) for a in answers[host]]
    monkeypatch.setattr(socket, "getaddrinfo", fake)
    assert EVERY in _said("anywhere.example")
    assert EVERY in _said("everywhere.example")
    assert EVERY not in _said("here.example")


def test_a_malformed_address_is_a_usage_error(capsys):
    """On the command line: exit 2, one line saying what is wrong, before anything
    starts."""
    with pytest.raises(SystemExit) as exited:
        main(["run", "robot.yaml", "--foxglove", "[::1"])
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert err.splitlines()[-1] == (
        "rocoma-can run: error: argument --foxglove: expected HOST:PORT, HOST, :PORT or "
        "[IPV6]:PORT, got '[::1': the '[' has no ']'")
    assert "Traceback" not in err


@pytest.mark.parametrize("verb", [["run", "robot.yaml"], ["demo"]])
def test_a_live_view_option_without_the_live_view_is_said(verb, capsys):
    """--foxglove-rate or --foxglove-allow-commands alone would be ignored: said, exit 2,
    before anything starts."""
    for options, said in ((["--foxglove-rate", "5"], "--foxglove-rate"),
                          (["--foxglove-allow-commands"], "--foxglove-allow-commands")):
        assert main([*verb, *options]) == 2
        captured = capsys.readouterr()
        assert f"{said} without --foxglove: there is no live view for it" in \
            captured.out + captured.err
        assert "Traceback" not in captured.out + captured.err
    args = build_parser().parse_args(["run", "robot.yaml", "--foxglove", "[::1]:0",
                                      "--foxglove-rate", "5"])
    assert foxglove_from_args(args) == FoxgloveConfig("::1", 0, rate=5.0)


@pytest.mark.parametrize("config", ["robot.yaml", "robots/arm.YML", "existing"])
def test_a_config_taken_as_the_address_is_said(config, tmp_path, monkeypatch, capsys):
    """``run --foxglove robot.yaml``: --foxglove (its value optional) takes the config as
    its address, and "required: config" alone does not say why. A word that looks like a
    config (.yaml, .yml, or a file that exists) gets the hint (a path is no host either:
    said first)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "existing").write_text("rate: 100\n")
    with pytest.raises(SystemExit) as exited:
        main(["run", "--foxglove", config])
    assert exited.value.code == 2
    err = capsys.readouterr().err
    wrong = ("argument --foxglove: expected HOST:PORT, HOST, :PORT or [IPV6]:PORT, got "
             f"{config!r}: {config!r} is not a host name or an IPv4 address" if "/" in config
             else "the following arguments are required: config")
    assert err.splitlines()[-1] == (
        f"rocoma-can run: error: {wrong}; --foxglove took {config!r} as its address: put "
        "the config first or write --foxglove=HOST:PORT")
    assert "Traceback" not in err


@pytest.mark.parametrize("words", [["--foxglove", "localhost"], ["--foxglove=robot.yaml"],
                                   ["--foxglove"]])
def test_no_hint_where_no_config_was_taken(words, tmp_path, monkeypatch, capsys):
    """A host, or an address written with '=' (meant as one): the usage error as
    argparse says it."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exited:
        main(["run", *words])
    assert exited.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        "rocoma-can run: error: the following arguments are required: config")
