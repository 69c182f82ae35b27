"""What reading a config's URDF costs, by its size: a chain of N links (a snake), each joint
revolute, read as check-config and ``run`` read it (rocoma_can.live.urdf.parse_urdf).

    .venv/bin/python benchmarks/urdf_read.py [--links 1000,4000,14000] [--repeat 3]

The largest default is about the largest robot the 2 MiB limit lets in (14,000 links,
1.8 MB). Linear reading keeps the time per link flat across the rows; the reading before
issue 53 compared every joint with every joint before it (16 s for 14,000 links).
"""
from __future__ import annotations

import argparse
import time

from _report import report, stats

from rocoma_can.live.urdf import parse_urdf


def chain(links: int) -> bytes:
    parts = ['<robot name="snake">', '<link name="l0"/>']
    for i in range(1, links):
        parts.append(f'<link name="l{i}"/><joint name="j{i}" type="revolute"><parent '
                     f'link="l{i - 1}"/><child link="l{i}"/><axis xyz="0 0 1"/></joint>')
    return ("\n".join(parts) + "</robot>").encode()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--links", default="1000,4000,14000",
                        help="comma-separated link counts")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="1000,4000 links, once")
    args = parser.parse_args()
    counts = [1000, 4000] if args.quick else [int(n) for n in args.links.split(",")]
    repeat = 1 if args.quick else max(1, args.repeat)
    rows, results = [], []
    for links in counts:
        text = chain(links)
        times = []
        for _ in range(repeat):
            start = time.perf_counter()
            parse_urdf(text, "snake.urdf")
            times.append(time.perf_counter() - start)
        s = stats(times)
        rows.append([links, len(text) / 1e6, s["median"] * 1e3, s["median"] / links * 1e6])
        results.append({"links": links, "mbytes": len(text) / 1e6,
                        "median_ms": s["median"] * 1e3,
                        "per_link_us": s["median"] / links * 1e6})
    report("urdf_read", "Reading a URDF: a chain of N links",
           ["links", "MB", "median ms", "µs per link"], rows, args=args, results=results)


if __name__ == "__main__":
    main()
