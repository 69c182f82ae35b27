"""CAN bus load of the cyclic traffic: which drive counts and rates fit on one bus.

    .venv/bin/python benchmarks/bus_load.py [--drives 1,6,12,24] [--rates 250,500,1000]

Computed, not measured: frames per cycle come from the driver's own PDO layouts
(drivers/plan/pdo_layout.py, the same ``layout_for`` the hardware layer uses) and bits per frame
from the classic-CAN formula the config check uses (rocoma_can.drivers.protocol.wire.frame_bits):
8n + 47 bits for n data bytes (with intermission), plus up to floor((34 + 8n - 1) / 4) stuff
bits in the worst case.
Per cycle: every drive's RPDOs and TPDOs and one SYNC; per second on top: the manager's and
every drive's heartbeat (1 byte each, --heartbeat-ms). "fits" means the worst case (full
stuffing) stays at or below --max-load percent of the bit rate.
"""
from __future__ import annotations

import argparse

from _report import report

from rocoma_can.drivers.plan.config import DriveConfig
from rocoma_can.drivers.plan.pdo_layout import layout_for
from rocoma_can.drivers.protocol.joints import JointMode
from rocoma_can.drivers.protocol.wire import frame_bits as wire_bits

BITRATES = (500_000, 1_000_000)
#: name -> (modes, feedback): the default drive and the leanest CSP drive
LAYOUTS = {
    "CSP + pos/vel/torque": ((JointMode.CSP,), ("position", "velocity", "torque")),
    "CSP + position only": ((JointMode.CSP,), ("position",)),
}


def frame_bits(n: int) -> tuple[int, int]:
    """(no stuffing, worst-case stuffing) bits of a classic 11-bit frame with n data bytes."""
    return int(wire_bits(n, worst_case=False)), int(wire_bits(n))


def drive_cycle(modes: tuple, feedback: tuple) -> tuple[int, int, int]:
    """(frames, nominal bits, worst bits) one drive exchanges per cycle."""
    layout = layout_for(DriveConfig("j", 1, 4096, 1.0, modes=modes, feedback=feedback))
    sizes = [p.size for p in layout.rpdos + layout.tpdos]
    bits = [frame_bits(n) for n in sizes]
    return len(sizes), sum(b[0] for b in bits), sum(b[1] for b in bits)


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drives", type=_ints, default=[1, 6, 12, 24])
    parser.add_argument("--rates", type=_ints, default=[250, 500, 1000], help="Hz")
    parser.add_argument("--heartbeat-ms", type=int, default=100)
    parser.add_argument("--max-load", type=float, default=100.0,
                        help="worst-case load in percent that still counts as fitting")
    parser.add_argument("--quick", action="store_true", help="same as the default (instant)")
    args = parser.parse_args()

    sync_nominal, sync_worst = frame_bits(0)
    hb_nominal, hb_worst = frame_bits(1)
    rows, data = [], []
    for layout_name, (modes, feedback) in LAYOUTS.items():
        frames, d_nominal, d_worst = drive_cycle(modes, feedback)
        for n in args.drives:
            heartbeats_per_s = (n + 1) * 1000.0 / args.heartbeat_ms
            for rate in args.rates:
                per_cycle = n * frames + 1
                nominal = rate * (n * d_nominal + sync_nominal) + heartbeats_per_s * hb_nominal
                worst = rate * (n * d_worst + sync_worst) + heartbeats_per_s * hb_worst
                loads = {b: (100.0 * nominal / b, 100.0 * worst / b) for b in BITRATES}
                fits = {b: loads[b][1] <= args.max_load for b in BITRATES}
                rows.append([layout_name, n, rate, per_cycle, round(per_cycle * rate),
                             *[f"{loads[b][0]:.0f}-{loads[b][1]:.0f}%"
                               f" {'fits' if fits[b] else 'NO'}" for b in BITRATES]])
                data.append({"layout": layout_name, "drives": n, "rate_hz": rate,
                             "frames_per_cycle": per_cycle, "frames_per_s": per_cycle * rate,
                             **{f"load_{b // 1000}k_percent": {"nominal": loads[b][0],
                                                                "worst": loads[b][1]}
                                for b in BITRATES},
                             **{f"fits_{b // 1000}k": fits[b] for b in BITRATES}})
    report("bus_load", "Cyclic bus load per drive count and rate (computed)",
           ["layout", "drives", "Hz", "frames/cycle", "frames/s", "500 kbit/s", "1 Mbit/s"],
           rows, args=args,
           notes=["load = no stuffing - worst-case stuffing; fits = worst case <= "
                  f"{args.max_load:g} %. Frames per cycle: RPDOs + TPDOs of every drive + "
                  "SYNC; heartbeats add (drives + 1) x 1-byte frames every "
                  f"{args.heartbeat_ms} ms. Arbitration latency and error frames are not "
                  "included: keep real buses well below 100 %."],
           results=data)


if __name__ == "__main__":
    main()
