"""tools/vcan-run's native way, exercised where the kernel has vcan: inside the vcan suite
(in the user-mode-linux guest here, or natively on a host with vcan). The runner must bring
missing or downed interfaces back when it may, and pass the exit status through."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

VCAN_RUN = Path(__file__).resolve().parents[2] / "tools" / "vcan-run"

PROBE = """
import os, sys
up = [int(open(f"/sys/class/net/{n}/flags").read(), 16) & 1 for n in ("vcan0", "vcan1")]
print(os.environ["ROCOMA_VCAN_RUNNER"], up)
sys.exit(5)
"""


def test_native_runner_restores_interfaces_and_passes_the_status(vcan_link):
    vcan_link("vcan0", "down")
    vcan_link("vcan1", "absent")

    result = subprocess.run([sys.executable, str(VCAN_RUN), sys.executable, "-c", PROBE],
                            env=dict(os.environ, ROCOMA_VCAN_MODE="native"),
                            capture_output=True, text=True, timeout=60)

    assert result.returncode == 5, result.stderr
    assert result.stdout == "native [1, 1]\n"
    assert "running natively" in result.stderr
