"""Reading a file a user names (a config's ``urdf:`` and ``eds:``, ``demo --eds``) so that
no name can hang the command: only a regular file is read.

Opening a FIFO waits for a writer and reading a character device may never end, so a
config naming one would hang ``check-config``, ``run`` or the demo for ever. The path is
looked at before it is opened (opening some devices does something), opened without
waiting (a FIFO swapped in meanwhile opens at once) and looked at again once open.
"""
from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

_NO_WAIT = getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0)


class NotRegularFile(OSError):
    """The path names something else than a regular file; ``strerror`` says what."""


def kind(mode: int) -> str | None:
    """What a file of this ``st_mode`` is when it is not a regular file; None when it is."""
    if stat.S_ISREG(mode):
        return None
    return next((kind for test, kind in (
        (stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device")) if test(mode)), "a special file")


def not_regular(path: str | Path) -> str | None:
    """What is wrong with ``path`` as a file to read later (a config's check: missing, or
    ``is a FIFO (named pipe), not a regular file``), None when it is a regular file."""
    try:
        what = kind(Path(path).stat().st_mode)
    except OSError as exc:
        return f": {exc.strerror or exc}"
    return None if what is None else f" is {what}, not a regular file"


def _regular(mode: int) -> None:
    what = kind(mode)
    if what is not None:
        raise NotRegularFile(errno.EINVAL, f"{what}, not a regular file")


def read_regular(path: str | Path, limit: int = -1) -> bytes:
    """The bytes of the regular file at ``path`` (at most ``limit``; -1: all); OSError when
    it cannot be read, NotRegularFile when it is no regular file."""
    _regular(os.stat(path).st_mode)
    with os.fdopen(os.open(path, os.O_RDONLY | _NO_WAIT), "rb") as f:
        _regular(os.fstat(f.fileno()).st_mode)
        return f.read(limit)


def yaml_problem(exc: Exception, source: str, text: str = "") -> str:
    """What a YAML reader said of the file ``source`` (``text``: what it read), as one line
    that names the file and the line: PyYAML names the stream it was handed (``<unicode
    string>`` for text read first, as every file here is, to bound its size) and spreads
    its message over several lines, with the offending line quoted."""
    problem_mark = getattr(exc, "problem_mark", None)
    if problem_mark is None:  # a ReaderError: a character YAML refuses, by its offset
        position = getattr(exc, "position", None)
        reason = getattr(exc, "reason", None) or str(exc).splitlines()[0]
        character = getattr(exc, "character", None)
        what = (f"{reason} (character #x{character:04x})" if isinstance(character, int)
                else str(reason))
        if isinstance(position, int) and text:
            line = text.count("\n", 0, position) + 1
            column = position - (text.rfind("\n", 0, position) + 1) + 1
            return f"{source}: line {line}, column {column}: not valid YAML: {what}"
        return f"{source}: not valid YAML: {what}"
    where = f"line {problem_mark.line + 1}, column {problem_mark.column + 1}"
    said = getattr(exc, "problem", None) or "not understood"
    context, context_mark = getattr(exc, "context", None), getattr(exc, "context_mark", None)
    if context:
        began = ""
        if context_mark is not None and (context_mark.line, context_mark.column) != (
                problem_mark.line, problem_mark.column):
            began = f" that began at line {context_mark.line + 1}, column " \
                    f"{context_mark.column + 1}"
        said += f" ({context}{began})"
    return f"{source}: {where}: not valid YAML: {said}"
