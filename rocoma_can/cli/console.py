"""How every ``rocoma-can`` verb speaks on its terminal: one format for every line.

Results go to stdout, messages to stderr, each line ``rocoma-can: TEXT``; a log record
says its level when it is not plain information (``rocoma-can: warning: ...``,
``rocoma-can: error: ...``, ``rocoma-can: debug: ...``) and, with ``-vv``, the logger it
comes from. ``run`` puts the local time in front of every line (``2026-12-07
18:07:53.383 rocoma-can: ...``): its console is the operator's record of the run, and its
audit lines (rocoma_can.audit: every operator request, state change and bring-up result)
go to stdout with its own, everything else to stderr. Library log lines (python-can's,
canopen's, the manager's) come through the same formatter, never in logging's default
layout beside the command's own.

Verbosity: by default WARNING and above (and ``run``'s audit lines); ``-v`` information from
every part; ``-vv`` debug, with each line's logger, and the library lines a command says
better itself (SAID_BY_US) unfiltered.

A reader that goes away (``rocoma-can status | head -3``): Python ignores SIGPIPE, so a
write then raises BrokenPipeError, which ended every verb in a traceback. The verbs stop
quietly instead, with stdout pointed at /dev/null (so the interpreter's last flush cannot
fail again), exit code PIPE_CLOSED (141, 128 + SIGPIPE, what a shell shows for ``yes |
head``). SIGPIPE is not set back to its default, which would end the process at once:
``run`` must never end without its torque-off because a socket or a pipe went away.
``run`` goes on when its stdout closes (a ``| tee`` that ended must not stop a robot): it
says so once on stderr and writes its audit lines there from then on.
"""
from __future__ import annotations

import logging
import os
import select
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from ..audit import AUDIT
from ..log_format import PROGRAM, ConsoleFormatter

#: library log lines a command says itself, better: logger -> how such a line begins.
#: canopen's SDO client logs an ERROR line each time a request times out (a drive not
#: answering, once per try); the command says what failed once, naming the drive and what
#: to check. python-can's socketcan logs one for a link it cannot open, then raises; the
#: command says it with the bus's name and what to do. Shown with -vv.
SAID_BY_US = {"canopen.sdo.client": ("Transfer aborted by client",),
              "can.interfaces.socketcan.socketcan": ("Could not access SocketCAN device",)}


def line(text: str) -> str:
    """A message of a verb's own, as every console line begins."""
    return f"{PROGRAM}: {text}"


def err(text: str) -> None:
    """A message (an error, a warning, what to do) on stderr."""
    print(line(text), file=sys.stderr, flush=True)


class _Stdout(logging.StreamHandler):  # type: ignore[type-arg]
    """The audit lines' handler (stdout). A reader gone (BrokenPipeError) is said once on
    stderr, and the lines go there from then on (see the module)."""

    def __init__(self) -> None:
        super().__init__(sys.stdout)
        self.closed = False

    def handleError(self, record: logging.LogRecord) -> None:
        if not isinstance(sys.exc_info()[1], BrokenPipeError) or self.closed:
            super().handleError(record)
            return
        self.closed = True
        point_stdout_at_devnull()
        self.setStream(sys.stderr)
        said = logging.LogRecord(record.name, logging.WARNING, __file__, 0,
                                 "stdout was closed (its reader ended); this run goes on, its "
                                 "lines go to stderr from now on", None, None)
        self.emit(said)
        self.emit(record)


class Console:
    """The logging set-up of one verb (see the module), undone by ``close``: main() runs in
    the tests' process too, once per command."""

    def __init__(self, verbose: int, clock: bool = False, audit: bool = False) -> None:
        self.root = logging.getLogger()
        self._levels: list[tuple[logging.Logger, int]] = []
        self._set(self.root, (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)])
        if audit and verbose < 1:
            self._set(logging.getLogger(AUDIT), logging.INFO)
        formatter = ConsoleFormatter(clock=clock, names=verbose >= 2)
        self.stdout = _Stdout()
        self.stdout.addFilter(_audit_line)
        self.stderr = logging.StreamHandler(sys.stderr)
        self.stderr.addFilter(lambda record: not _audit_line(record))
        self._handlers: list[logging.Handler] = [self.stdout, self.stderr]
        for handler in self._handlers:
            handler.setFormatter(formatter)
            self.root.addHandler(handler)
        self._filters: list[tuple[logging.Logger, Callable[[logging.LogRecord], bool]]] = []
        if verbose < 2:
            for name in SAID_BY_US:
                self.hide(name, SAID_BY_US[name])

    def _set(self, logger: logging.Logger, level: int) -> None:
        self._levels.append((logger, logger.level))
        logger.setLevel(level)

    def hide(self, logger: str, beginnings: tuple[str, ...]) -> None:
        """Leave out ``logger``'s lines that begin so (said better by the command)."""
        def said(record: logging.LogRecord) -> bool:
            return not record.getMessage().startswith(beginnings)
        target = logging.getLogger(logger)
        target.addFilter(said)
        self._filters.append((target, said))

    def close(self) -> None:
        for handler in self._handlers:
            self.root.removeHandler(handler)
        for logger, said in self._filters:
            logger.removeFilter(said)
        for logger, level in reversed(self._levels):
            logger.setLevel(level)


def _audit_line(record: logging.LogRecord) -> bool:
    return record.name == AUDIT and record.levelno < logging.WARNING


@contextmanager
def console(verbose: int, clock: bool = False, audit: bool = False) -> Iterator[Console]:
    made = Console(verbose, clock, audit)
    try:
        yield made
    finally:
        made.close()


def stdout_gone() -> bool:
    """Whether stdout is a pipe or socket whose reader has gone (poll says POLLERR for a
    pipe without readers): a BrokenPipeError on anything else is a real failure."""
    try:
        fd = sys.__stdout__.fileno() if sys.__stdout__ is not None else 1
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        return any(events & (select.POLLERR | select.POLLHUP)
                   for _, events in poller.poll(0))
    except (OSError, ValueError, AttributeError):
        return False


def point_stdout_at_devnull() -> None:
    """stdout's file descriptor onto /dev/null: what is still buffered, and the
    interpreter's flush at exit, go nowhere instead of raising again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        fd = sys.__stdout__.fileno() if sys.__stdout__ is not None else 1
        os.dup2(devnull, fd)
        os.close(devnull)
    except (OSError, ValueError):
        pass


class ThreadedLines:
    """``print`` for a verb whose result lines come from several threads (the demo's
    operator, its status lines, the recorder's announcements): a reader gone is found by
    whichever thread writes next, and there a BrokenPipeError ended that thread in a
    traceback while the others went on. Here the first one to find it points stdout at
    /dev/null (module docstring) and the lines after it go nowhere; the verb ends with
    PIPE_CLOSED when ``gone``."""

    def __init__(self) -> None:
        self.gone = False

    def __call__(self, text: str) -> None:
        if self.gone:
            return
        try:
            print(text, flush=True)
        except BrokenPipeError:
            if not stdout_gone():
                raise
            self.gone = True
            point_stdout_at_devnull()
