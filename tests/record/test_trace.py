"""rocoma_can/record/trace.py (reading), rocoma_can/cli/record.py (``export``), record/plot.py:
a trace that is not one, is foreign, cut short or damaged is read up to where it can be, or
said in one line; an output that would overwrite the input or is not a file is refused."""
from __future__ import annotations

import csv

import pytest

from rocoma_can.cli.main import main


def test_export_of_a_file_that_is_not_a_trace_is_a_clear_error(tmp_path, capsys):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"junk")
    earlier = tmp_path / "junk.csv"
    earlier.write_text("an earlier export\n")
    assert main(["export", str(junk)]) == 2
    assert capsys.readouterr().err == f"rocoma-can: {junk}: not a rocoma-can trace: " \
                                      "struct.error: unpack requires a buffer of 8 bytes\n"
    # nothing lost: the earlier CSV stands, no partial file is left behind
    assert earlier.read_text() == "an earlier export\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk.csv", "junk.mcap"]


@pytest.mark.parametrize("args", [["data.csv"], ["t.mcap", "--csv", "t.mcap"]])
def test_export_never_overwrites_its_own_input(tmp_path, capsys, args, monkeypatch):
    monkeypatch.chdir(tmp_path)
    source = tmp_path / args[0]
    source.write_bytes(b"the only copy")
    assert main(["export", *args]) == 2
    assert "would overwrite the trace it is read from" in capsys.readouterr().err
    assert source.read_bytes() == b"the only copy"


def test_plot_of_a_file_that_is_not_a_trace_is_a_clear_error(tmp_path, capsys):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"junk")
    assert main(["plot", str(junk)]) == 2
    assert main(["plot", str(tmp_path / "missing.mcap")]) == 2
    err = capsys.readouterr().err
    assert "junk.mcap: not a rocoma-can trace" in err and "missing.mcap" in err


JOINTS = ("hip", "knee")


def cycle(k: int, joints: int = 2) -> dict:
    """A well-formed /rocoma/cycle message, as the writer makes them."""
    from rocoma_can.record.trace import JOINT_FIELDS
    return {"t": 0.01 * k, "period": 0.01, "work": 0.001, "late": 0.0, "state": "OK",
            "controller": "pd", **{f: [float(j) for j in range(joints)] for f in JOINT_FIELDS}}


def write_mcap(path, cycles, events=(), encoding: str = "json") -> None:
    """An MCAP file with our schemas and channels but ``cycles`` (objects to JSON-encode, or
    raw bytes) and ``events`` as given: what another program could put there."""
    import json

    from mcap.writer import Writer

    from rocoma_can.record.trace import EVENT_SCHEMA, cycle_schema
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start()
        schemas = [writer.register_schema(name=name, encoding="jsonschema",
                                          data=json.dumps(schema).encode())
                   for name, schema in (("rocoma_can.Cycle", cycle_schema(JOINTS)),
                                        ("rocoma_can.ManagerEvent", EVENT_SCHEMA))]
        channels = [writer.register_channel(topic=topic, message_encoding=encoding,
                                            schema_id=schema)
                    for topic, schema in zip(("/rocoma/cycle", "/rocoma/event"), schemas)]
        for channel, messages in zip(channels, (cycles, events)):
            for k, msg in enumerate(messages):
                data = msg if isinstance(msg, bytes) else json.dumps(msg).encode()
                writer.add_message(channel_id=channel, log_time=10**9 + k * 10**7,
                                   publish_time=10**9 + k * 10**7, data=data)
        writer.finish()


def without(msg: dict, key: str) -> dict:
    return {k: v for k, v in msg.items() if k != key}


FOREIGN = {  # name: (cycles, events, encoding, why)
    "missing-field": ([without(cycle(0), "command_mode")], [], "json",
                      "/rocoma/cycle message 1 has no 'command_mode' array"),
    "missing-scalar": ([cycle(0), without(cycle(1), "state")], [], "json",
                       "/rocoma/cycle message 2 has no 'state'"),
    "list-not-object": ([[1, 2, 3]], [], "json",
                        "/rocoma/cycle message 1 is an array ([1, 2, 3]), not an object"),
    "strings-for-numbers": ([{**cycle(0), "position": ["0.1", "0.2"]}], [], "json",
                            "/rocoma/cycle message 1: 'position' holds text ('0.1'), not a "
                            "number or null"),
    "string-period": ([{**cycle(0), "period": "10ms"}], [], "json",
                      "/rocoma/cycle message 1: 'period' is text ('10ms'), not a number "
                      "or null"),
    "joint-counts-differ": ([cycle(0), cycle(1, joints=3)], [], "json",
                            "/rocoma/cycle message 2: 'position' has 3 joints, the trace 2"),
    "array-not-list": ([{**cycle(0), "torque": {"hip": 1.0}}], [], "json",
                       "/rocoma/cycle message 1: 'torque' is an object ({'hip': 1.0}), not an "
                       "array"),
    "event-not-object": ([cycle(0)], ["e-stop"], "json",
                         "/rocoma/event message 1 is text ('e-stop'), not an object"),
    "cdr-encoding": ([b"\x00\x01\x00\x00"], [], "cdr",
                     "/rocoma/cycle is encoded as 'cdr', not JSON"),
    "not-json": ([b"\xff\x00garbage"], [], "json",
                 "a /rocoma/cycle message is not JSON: b'\\xff\\x00garbage'"),
}


@pytest.mark.parametrize("verb", ["plot", "export"])
@pytest.mark.parametrize("name", FOREIGN)
def test_a_trace_with_foreign_content_is_said_in_one_line(tmp_path, capsys, name, verb):
    cycles, events, encoding, why = FOREIGN[name]
    path = tmp_path / "foreign.mcap"
    write_mcap(path, cycles, events, encoding)
    assert main([verb, str(path)]) == 2
    captured = capsys.readouterr()
    assert captured.err == f"rocoma-can: {path}: not a rocoma-can trace: {why}\n"
    assert captured.out == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["foreign.mcap"]  # no PNG, no CSV


def write_chunked(path, cycles: int, chunk_size: int) -> None:
    """``cycles`` cycle messages written as a recording writes them (mcap_file.py: chunks of
    ``chunk_size`` bytes, then the summary)."""
    import json

    from rocoma_can.record.mcap_file import McapFile
    from rocoma_can.record.trace import cycle_schema
    with open(path, "wb") as stream:
        f = McapFile(stream, chunk_size=chunk_size)
        channel = f.channel("/rocoma/cycle", "json", f.schema(
            "rocoma_can.Cycle", "jsonschema", json.dumps(cycle_schema(JOINTS)).encode()))
        for k in range(cycles):
            f.add(channel, 10**9 + k * 10**7, json.dumps(cycle(k)).encode())
        f.finish()


def _cut(data: bytes) -> bytes:
    return data[:int(len(data) * 0.6)]


def _damaged(data: bytes) -> bytes:
    middle = len(data) // 2
    return data[:middle] + b"\xff" * 64 + data[middle + 64:]


#: how a file is spoilt -> its bytes from a whole file's, the note's start and end
SPOILT = {
    "cut": (_cut, "cut short (", "the run that wrote it did not close it): read up to the cut"),
    "damaged": (_damaged, "damaged (",
                "messages: a part of it cannot be read): read up to the damage")}


@pytest.mark.parametrize("verb", ["plot", "export"])
@pytest.mark.parametrize("how", SPOILT)
def test_a_file_cut_short_or_damaged_is_read_up_to_it(tmp_path, capsys, verb, how):
    """A run killed (SIGKILL, the power) or a full disk leaves a trace without its summary,
    its last chunk half written: it was "not a rocoma-can trace" (exit 2), though every whole
    chunk before the cut holds its cycles. A whole trace with a chunk damaged in its middle
    (a bad sector, a copy gone wrong) was "not a rocoma-can trace: ZstdError: ..." (exit 2)
    too. They are plotted / exported up to it, and a line says what it was."""
    spoil, starts, ends = SPOILT[how]
    good = tmp_path / "good.mcap"
    write_chunked(good, 300, chunk_size=4096)
    path = tmp_path / "spoilt.mcap"
    path.write_bytes(spoil(good.read_bytes()))
    good.unlink()
    assert main([verb, str(path)]) == 0
    captured = capsys.readouterr()
    (note,) = captured.err.splitlines()
    assert note.startswith(f"rocoma-can: {path}: {starts}") and note.endswith(ends), note
    if verb == "export":
        rows = int(captured.out.split()[0])
        assert 0 < rows < 300
        lines = (tmp_path / "spoilt.csv").read_text().splitlines()
        assert len(lines) == rows + 1 and lines[1].startswith("1000000000,0.0,")
    else:
        assert (tmp_path / "spoilt.png").stat().st_size > 0


@pytest.mark.parametrize("verb", ["plot", "export"])
@pytest.mark.parametrize("cut", ["in its first chunk", "garbage", "empty"])
def test_a_cut_or_garbage_file_is_said_in_one_line(tmp_path, capsys, cut, verb):
    """Nothing whole in it (cut inside its first chunk), or not MCAP at all."""
    good = tmp_path / "good.mcap"
    write_chunked(good, 200, chunk_size=1 << 20)
    data = good.read_bytes()
    path = tmp_path / "bad.mcap"
    path.write_bytes({"in its first chunk": data[:60],  # (magic and header: 35 bytes)
                      "garbage": bytes(range(256)) * 64, "empty": b""}[cut])
    good.unlink()
    assert main([verb, str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"rocoma-can: {path}: not a rocoma-can trace: ") \
        and err.count("\n") == 1, err
    assert err.endswith({
        "in its first chunk": "\n",  # the reader's words for where the cut fell
        "garbage": "InvalidMagic: not a valid MCAP file, invalid magic: (0, 1, 2, 3, 4, 5, 6, "
                   "7)\n",
        "empty": "not a rocoma-can trace: EndOfFile\n"}[cut]), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.mcap"]


def test_a_well_formed_foreign_trace_plots_and_exports_with_joint_names(tmp_path, capsys):
    """Beside the checks: a file written by another program to our schema is a trace; other
    programs' channels in it are passed over."""
    path = tmp_path / "ok.mcap"
    write_mcap(path, [cycle(k) for k in range(20)], [{"kind": "emergency_stop",
                                                     "state": "EMERGENCY", "cause": "test"}])
    assert main(["plot", str(path)]) == 0
    assert main(["export", str(path)]) == 0
    with open(tmp_path / "ok.csv") as stream:
        header = next(csv.reader(stream))
    assert header[:7] == ["log_time_ns", "t", "period", "work", "late", "state", "controller"]
    assert header[7:9] == ["position[hip]", "position[knee]"]
    assert header[-1] == "error_code[knee]"


def test_export_into_a_directory_that_is_a_file_is_one_line(tmp_path, capsys):
    """The partial file's clean-up cannot remove what could not be made: no second error."""
    path = tmp_path / "ok.mcap"
    write_mcap(path, [cycle(0)])
    blocker = tmp_path / "file"
    blocker.write_text("a file, not a directory")
    out = blocker / "sub" / "t.csv"
    assert main(["export", str(path), "--csv", str(out)]) == 2
    assert capsys.readouterr().err == \
        f"rocoma-can: {out}: cannot write the CSV: Not a directory\n"
    assert blocker.read_text() == "a file, not a directory"


def test_export_to_dash_writes_the_rows_on_stdout_and_no_file(tmp_path, capsys, monkeypatch):
    """``--csv -`` is stdout, as for csvkit and the shell's tools: the rows there, what is
    said on stderr, no file named ``-``."""
    path = tmp_path / "ok.mcap"
    write_mcap(path, [cycle(k) for k in range(5)])
    monkeypatch.chdir(tmp_path)
    assert main(["export", str(path), "--csv", "-"]) == 0
    said = capsys.readouterr()
    rows = list(csv.reader(said.out.splitlines()))
    assert rows[0][:2] == ["log_time_ns", "t"] and len(rows) == 1 + 5
    assert said.err == "rocoma-can: 5 cycles written to stdout\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ok.mcap"]
