"""The hint an unknown name gets: the nearest known one (``did_you_mean``). Shared by every
place that refuses a name, so a typo is answered alike wherever it is made: a verb or an
option on the command line, a python-can interface, a plugin's entry point."""
from __future__ import annotations

import difflib
from collections.abc import Iterable


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """The hint an unknown name gets: ", did you mean 'x'?" for the nearest of ``choices``,
    "" when none is near."""
    close = difflib.get_close_matches(word, list(choices), n=1)
    return f", did you mean {close[0]!r}?" if close else ""
