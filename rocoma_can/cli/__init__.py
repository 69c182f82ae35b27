"""The ``rocoma-can`` command: main (the parser; each verb's module registers itself),
commands (``run``, ``check-config`` and the verbs that talk to a running manager), record
(``record``, ``export``, ``plot``), live (``status --watch``), scaffold (``new-controller``),
scan (``scan``, ``lss``), init_config (``init-config``), doctor (``doctor``), demo (the
whole system on in-process buses), demo_config (its drives and config), demo_sim (its
simulated drives, in a process of their own), demo_probe (its check of the loop's
torque-off frames) and demo_stops (an operator's e-stop ends its walk-through).
``rocoma-can fleet`` lives with the fleet (fleet/client.py), ``rocoma-can sim`` with the
simulator (drivers/sim/cli.py).
"""
from __future__ import annotations

from .main import main

__all__ = ["main"]
