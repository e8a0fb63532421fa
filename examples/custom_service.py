"""A service with its own metadata kind: ``python examples/custom_service.py``.

The service ``thermo`` offers ``thermo/celsius`` whose metadata follows its own XSD
(``examples/temperature.xsd``). Every put is checked against it, so a reading the
schema forbids (NaN, below absolute zero) is refused before anything is stored. The node
then reads the readings back by time and picks a field out of the metadata.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from middleware import (
    NetworkConfig,
    Node,
    SchemaError,
    add_network_arguments,
    field_text,
    make_metadata,
    network_from_args,
    parse_untrusted,
    register_kind,
)

SCHEMA = Path(__file__).resolve().parent / "temperature.xsd"


def main(network: NetworkConfig, *, readings: list[float]) -> int:
    register_kind("temperature", SCHEMA)
    with Node("thermo", network) as node:  # a service node is a client too
        celsius = node.offer("celsius", kind="temperature")
        for value in readings:
            timestamp_ns = time.time_ns()
            metadata = make_metadata(
                "temperature", timestamp_ns, {"celsius": value, "sensor": "bench-1"}
            )
            try:
                celsius.put(timestamp_ns, b"", metadata)
                print(f"stored {value} C", flush=True)
            except SchemaError as exc:
                print(f"refused {value} C: {exc}", flush=True)
        for element in node.query("thermo/celsius"):
            root = parse_untrusted(element.metadata)
            print(f"read {field_text(root, 'celsius')} C from {field_text(root, 'sensor')}")
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(
        prog="custom_service", description=__doc__.splitlines()[0].replace("``", "")
    )
    add_network_arguments(parser)
    parser.add_argument(
        "readings", nargs="*", type=float, default=[21.5, math.nan, -300.0, 22.0], help="C"
    )
    args = parser.parse_args()
    raise SystemExit(main(network_from_args(args), readings=args.readings))
