"""Where rocoma-can keeps what it writes when no option says where: the state directory
(XDG_STATE_HOME), for flight records and the demo's recordings."""
from __future__ import annotations

import os
from pathlib import Path


def state_dir(*parts: str) -> Path:
    """$XDG_STATE_HOME/rocoma-can/PARTS (~/.local/state/rocoma-can/...): where flight
    records and the demo's recordings go by default."""
    state = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(state, "rocoma-can", *parts)


def default_flight_dir() -> Path:
    return state_dir("flight")

