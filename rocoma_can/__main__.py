"""``python -m rocoma_can``: the ``rocoma-can`` command, as the console script runs it."""
import sys

from .cli.main import main

sys.exit(main())
