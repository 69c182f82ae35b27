"""The ``rocoma-can`` command, a module per group of verbs: main is the parser, and each verb's
module registers itself (``run``, the operator verbs, ``fleet``, ``sim``, ``record`` ...; the
demo is the package demo/). What the verbs share: console (how every verb speaks), args,
hints, exit_codes. The modules: the module map in docs/architecture.md (tools/module-map
writes it from their docstrings).
"""
from __future__ import annotations

from .main import main

__all__ = ["main"]
