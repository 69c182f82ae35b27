"""The one format of every line rocoma-can writes on a terminal: ``[TIME ]rocoma-can:
[LEVEL: ][WHO: ][LOGGER: ]MESSAGE``. The CLI's console (cli/console.py) and the recording's
writer process (record/writer.py), whose lines come out on ``run``'s stderr, both use it.
"""
from __future__ import annotations

import logging

PROGRAM = "rocoma-can"

_LEVEL_WORDS = ((logging.ERROR, "error: "), (logging.WARNING, "warning: "),
                (logging.INFO, ""), (logging.NOTSET, "debug: "))


def level_word(levelno: int) -> str:
    """"error: ", "warning: ", "" (information) or "debug: "."""
    return next(word for level, word in _LEVEL_WORDS if levelno >= level)


class ConsoleFormatter(logging.Formatter):
    """``[TIME ]rocoma-can: [LEVEL: ][WHO: ][LOGGER: ]MESSAGE``, and a traceback where a
    record carries one (a bug's: it is kept whole). ``clock``: the local time in front
    (``run``'s lines); ``names``: the logger's name (``-vv``); ``who``: which process says
    it, when it is not the command's own (the recording's writer)."""

    def __init__(self, clock: bool = False, names: bool = False, who: str = "") -> None:
        super().__init__()
        self.clock, self.names, self.who = clock, names, who

    def format(self, record: logging.LogRecord) -> str:
        when = (f"{self.formatTime(record, '%Y-%m-%d %H:%M:%S')}.{int(record.msecs):03d} "
                if self.clock else "")
        who = f"{self.who}: " if self.who else ""
        name = f"{record.name}: " if self.names else ""
        text = (f"{when}{PROGRAM}: {level_word(record.levelno)}{who}{name}"
                f"{record.getMessage()}")
        if record.exc_info:
            text += "\n" + self.formatException(record.exc_info)
        return text
