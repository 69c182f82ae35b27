"""The exit codes of every ``rocoma-can`` command (``rocoma-can sim`` too): one set, since
scripts and the fleet client's ``--zenoh`` path must mean the same thing by each (docs/cli.md:
"Exit codes")."""
from __future__ import annotations

OK = 0         # done (a switch: SWITCHED or RUNNING)
FAILED = 1     # the manager refused, or the operation failed
USAGE = 2      # bad arguments or configuration (argparse exits with 2 too)
NO_ANSWER = 3  # nobody answered within the timeout
INTERRUPTED = 130  # Ctrl-C (128 + SIGINT, as a shell reports it)
PIPE_CLOSED = 141  # stdout's reader went away (`| head`): 128 + SIGPIPE, as a shell reports it
