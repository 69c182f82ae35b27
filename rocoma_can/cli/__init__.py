"""The ``rocoma-can`` command, a module per group of verbs: main (the parser; each verb's
module registers itself), run (``run``, ``check-config``), operator_verbs (``switch``,
``estop``, ``failproof``, ``clear``, ``recover``, ``home``, ``status``, ``list``: the
verbs that talk to a running manager), status_watch (``status --watch``), fleet
(``fleet`` and the operator verbs' ``--zenoh`` path), record (``record``, ``export``,
``plot``), scan (``scan``, ``lss``), init_config (``init-config``, with device_match: a
node's device file), doctor (``doctor``), scaffold (``new-controller``), sim (``sim``:
simulated drives on a CAN interface) and demo/ (``demo``: the whole system on in-process
buses). What they share: console (how every verb speaks), args (argparse types), hints
(what a refusal says to do), exit_codes, foxglove_args (``--foxglove`` for run and demo),
state_dirs (where they write by default).
"""
from __future__ import annotations

from .main import main

__all__ = ["main"]
