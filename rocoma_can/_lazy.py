"""Package attributes imported on first use (PEP 562), for the package ``__init__`` files.

Why: every ``rocoma-can`` start imports the package; a CLI verb that only talks to a running
manager over the bus must not import numpy and the manager core each time (seconds on a slow
bench machine, where the machine's own control loop competes with that start)."""
from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any


def lazy_exports(package: str, where: dict[str, str]) -> tuple[Callable[[str], Any],
                                                                 Callable[[], list[str]]]:
    """``__getattr__`` and ``__dir__`` for ``package``: name -> its submodule in ``where``.
    A name, once imported, is stored in the package so later lookups never come here."""
    namespace = importlib.import_module(package).__dict__

    def __getattr__(name: str) -> Any:
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted({*namespace, *where})
    return __getattr__, __dir__
