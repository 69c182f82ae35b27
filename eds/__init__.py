"""EDS files shipped with rocoma-can, importable wherever the package is installed."""
from __future__ import annotations

from importlib import resources
from pathlib import Path

CIA402_DRIVE = "cia402_drive.eds"
MANAGER_NODE = "rocoma_manager.eds"


def path(name: str) -> Path:
    """Filesystem path of a shipped EDS file (canopen.import_od needs a path, not a stream)."""
    p = Path(str(resources.files(__name__).joinpath(name)))
    if not p.is_file():
        raise FileNotFoundError(f"rocoma-can ships no EDS named {name!r} (looked in {p.parent})")
    return p
