"""``python -m services.lib.quality.bench``: microseconds per frame of each blur mode."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from ._bench import bench_quality


def main(argv: Sequence[str] | None = None) -> int:
    """Print the timing of every blur mode; ``--json`` for machines."""
    parser = argparse.ArgumentParser(
        prog="python -m services.lib.quality.bench", description=__doc__
    )
    parser.add_argument("--frames", type=int, default=500, help="frames per mode (500)")
    parser.add_argument("--exposure-ms", type=float, default=60.0, help="exposure (60 ms)")
    parser.add_argument("--gyro-hz", type=float, default=500.0, help="gyro rate (500 Hz)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    results = bench_quality(
        frames=args.frames,
        exposure_ns=round(args.exposure_ms * 1e6),
        gyro_rate_hz=args.gyro_hz,
    )
    if args.json:
        print(json.dumps(results))
        return 0
    print(f"blur estimate, {args.exposure_ms:g} ms exposure, {args.gyro_hz:g} Hz gyro:")
    for name, micros in results.items():
        print(f"  {name:<18} {micros:8.1f} us/frame")
    return 0


if __name__ == "__main__":
    sys.exit(main())
