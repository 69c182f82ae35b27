"""A plugin module that fails on import (for tests/test_plugins.py)."""
raise RuntimeError("this module is broken on purpose")
