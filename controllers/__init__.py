"""Controller plugins: failproof torque-off, emergency controllers, PD, trajectories.

Each is found by its entry-point name (pyproject.toml); the modules: the module map in
docs/architecture.md (tools/module-map writes it from their docstrings)."""
from __future__ import annotations

from importlib import resources
from pathlib import Path


def example_path(name: str = "tuple.yaml") -> Path:
    """A controller configuration shipped in controllers/examples/ (package data)."""
    path = Path(str(resources.files(__name__).joinpath("examples").joinpath(name)))
    if not path.is_file():
        raise FileNotFoundError(f"no example controller configuration {name!r} in {path.parent}")
    return path
