"""``framegate query``: elements of a buffer by time range, newest N, or nearest to a time."""

from __future__ import annotations

import argparse
import base64
import os
import re
import sys
from pathlib import Path
from typing import Any

from middleware import (
    BufferInfo,
    DataObject,
    FramegateError,
    Node,
    QueryError,
    TimeRange,
    now_ns,
    parse_duration_ns,
    parse_time_ns,
    parse_untrusted,
    printable,
)
from services.lib.argtypes import positive_int
from services.lib.files import OutputError, create_file, open_directory

from ._common import (
    command_parser,
    counted,
    format_bytes,
    format_ns,
    format_seconds,
    network,
    print_json,
)
from ._fields import decode_metadata
from ._target import add_timeout_argument, producer_offset_ns, resolve

# With no selection at all, a query returns this many of the newest elements: a camera
# buffer can hold gigabytes, and nobody wants them all by accident.
DEFAULT_LAST = 10
# Metadata fields shown per row of the table.
TABLE_FIELDS = 3

_TIME_HELP = "now, -5s (relative), 2026-11-22T14:00:00.5Z (RFC 3339) or integer ns"
_RELATIVE = re.compile(r"^[+-]\s*(\d|\.\d)")
_NOW = re.compile(r"now\((.*)\)", re.DOTALL)
# Anything that starts like a number (`-5s`, and the typo `-5x`, which then gets a clear
# "bad time" instead of argparse's "expected one argument").
_NEGATIVE_TIME = re.compile(r"^-(\d|\.\d)")


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "query",
        "print (or save) the elements of a buffer in a time range",
        json_flag=True,
    )
    parser.add_argument("target", metavar="SERVICE/BUFFER", help="the buffer, e.g. camera/images")
    parser.add_argument("--from", dest="start", metavar="TIME", help=f"first time: {_TIME_HELP}")
    parser.add_argument("--to", dest="end", metavar="TIME", help=f"last time: {_TIME_HELP}")
    parser.add_argument(
        "--last",
        type=positive_int,
        metavar="N",
        help=f"only the newest N (of the range, if given); default {DEFAULT_LAST} with no range",
    )
    parser.add_argument("--at", metavar="TIME", help="the one element nearest to TIME")
    parser.add_argument(
        "--save",
        metavar="DIR",
        type=Path,
        help="write payloads (raw frames as PNG, else .bin) and metadata (.xml) to DIR; "
        "existing files and links are refused",
    )
    parser.add_argument(
        "--force", action="store_true", help="with --save: replace existing files (never links)"
    )
    parser.add_argument(
        "--with-payload", action="store_true", help="with --json: include payloads as base64"
    )
    add_timeout_argument(parser)
    # Let `--from -5s` mean a relative time, not an unknown option: argparse only takes
    # values that look like negative numbers, and asks this (private) matcher which do.
    parser._negative_number_matcher = _NEGATIVE_TIME
    parser.epilog = "Relative times count back from the service's clock, not this host's."
    parser.set_defaults(func=run)


def parse_cli_time(text: str, flag: str) -> tuple[int, bool]:
    """(nanoseconds, relative): relative values are offsets from "now"."""
    value = text.strip()
    try:
        if value == "now":
            return 0, True
        now_match = _NOW.fullmatch(value)
        if now_match:
            inner = now_match.group(1).strip()
            return (parse_duration_ns(inner) if inner else 0), True
        if _RELATIVE.match(value) and not re.fullmatch(r"[+-]?\d+", value):
            return parse_duration_ns(value.lstrip("+")), True
        return parse_time_ns(value), False
    except QueryError as exc:
        if re.fullmatch(r"[+-]?\d+", value):
            # Integer ns, of the right form but out of range: say so, and the range.
            raise QueryError(f"{flag}: {exc}") from exc
        raise QueryError(f"bad time {text!r} for {flag}: write {_TIME_HELP}") from exc


def _resolve_time(spec: tuple[int, bool] | None, now_ns: int) -> int | None:
    if spec is None:
        return None
    value, relative = spec
    return now_ns + value if relative else value


def run(args: argparse.Namespace) -> int:
    # Check every flag before touching the network: a typo should fail at once.
    start = parse_cli_time(args.start, "--from") if args.start is not None else None
    end = parse_cli_time(args.end, "--to") if args.end is not None else None
    at = parse_cli_time(args.at, "--at") if args.at is not None else None
    if at is not None and (start is not None or end is not None or args.last is not None):
        raise QueryError("--at stands alone: do not combine it with --from, --to or --last")
    if args.last is not None and args.last < 1:
        raise QueryError(f"--last {args.last}: ask for at least 1 element")
    if args.with_payload and not args.json:
        raise QueryError("--with-payload only applies to --json output")
    if args.force and args.save is None:
        raise QueryError("--force only applies to --save")
    with Node(network=network(args)) as node:
        service, buffer = resolve(node, args.target, args.timeout)
        # Relative times in the service's clock (its stamps are), and its replies alone
        # when one session answers as it: a peer's clock or elements are not its.
        now = now_ns() + producer_offset_ns(node, service.service, args.timeout)
        session = node.service_session(service.service)
        timeout_s = max(5.0, args.timeout)
        if at is not None:
            at_ns = _resolve_time(at, now)
            assert at_ns is not None
            TimeRange(at_ns, None)  # refuses a time outside 0..2^63-1 with a QueryError
            elements = [node.nearest(args.target, at_ns, timeout_s=timeout_s, session=session)]
            if note := retention_note(buffer, at_ns):  # the nearest is then the oldest
                print(f"note: {note.replace('range starts', 'time --at is', 1)}", file=sys.stderr)
        else:
            rng = None
            if start is not None or end is not None:
                rng = TimeRange(_resolve_time(start, now), _resolve_time(end, now))
                if (
                    rng.start_ns is not None
                    and rng.end_ns is not None
                    and rng.start_ns > rng.end_ns
                ):
                    raise QueryError(f"--from {args.start} is after --to {args.end}")
            last = args.last if args.last is not None or rng is not None else DEFAULT_LAST
            elements = node.query(
                args.target, time_range=rng, last=last, timeout_s=timeout_s, session=session
            )
            if rng is not None and (note := retention_note(buffer, rng.start_ns)):
                print(f"note: {note}", file=sys.stderr, flush=True)
    saved = _save_all(args.save, elements, args.force) if args.save is not None else {}
    if args.json:
        rows = [_element_json(e, saved.get(e.timestamp_ns), args.with_payload) for e in elements]
        print_json({"target": args.target, "count": len(elements), "elements": rows})
        return 0
    _print_table(elements)
    if args.save is not None:
        print(f"saved {counted(len(elements), 'element')} to {args.save}")
    return 0


def retention_note(buffer: BufferInfo, start_ns: int | None) -> str | None:
    """What a range that starts before the buffer's oldest element cannot get, or None.

    A buffer keeps only its retention's worth: the table alone would not say that the
    first minute of `--from -60s` is gone (or was never put), as `ros2 bag` cannot either.
    """
    if start_ns is None or buffer.oldest_ns is None or start_ns >= buffer.oldest_ns:
        return None
    r = buffer.retention
    limits = [
        f"max {r.max_count} elements" if r.max_count is not None else "",
        f"max {format_bytes(r.max_bytes)}" if r.max_bytes is not None else "",
        f"max age {r.max_age_ns / 1e9:g} s" if r.max_age_ns is not None else "",
    ]
    kept = ", ".join(x for x in limits if x) or "no limit"
    return (
        f"the range starts {format_seconds((buffer.oldest_ns - start_ns) / 1e9)} before "
        f"{buffer.name}'s oldest element ({format_ns(buffer.oldest_ns)}); it keeps {kept}, "
        "so what is older is gone or was never put (framegate info "
        f"{buffer.name})"
    )


def summarize(metadata: bytes) -> tuple[str, dict[str, str]]:
    """The kind and the leaf fields directly under the metadata root."""
    try:
        root = parse_untrusted(metadata)
    except FramegateError:
        return "?", {}
    fields: dict[str, str] = {}
    for child in root:
        if not isinstance(child.tag, str) or len(child):
            continue
        fields[str(child.tag).rsplit("}", 1)[-1]] = (child.text or "").strip()
    return str(root.get("kind", "?")), fields


def _element_json(
    element: DataObject, files: list[str] | None, with_payload: bool
) -> dict[str, Any]:
    kind, fields = decode_metadata(element.metadata)  # typed: numbers as JSON numbers
    row: dict[str, Any] = {
        "timestamp_ns": element.timestamp_ns,
        "time": format_ns(element.timestamp_ns),
        "kind": kind,
        "payload_bytes": len(element.payload),
        "fields": fields,
        "metadata": element.metadata.decode("utf-8", errors="replace"),
    }
    if with_payload:
        row["payload_base64"] = base64.b64encode(element.payload).decode("ascii")
    if files is not None:
        row["files"] = files
    return row


def _print_table(elements: list[DataObject]) -> None:
    if not elements:
        print("no elements")
        return
    print(f"{'TIME':<28} {'TIMESTAMP_NS':>20}  {'KIND':<10} {'SIZE':>10}  FIELDS")
    for e in elements:
        kind, fields = summarize(e.metadata)
        kind = printable(kind, 24)  # a producer's text: one line, no escape sequences
        shown = " ".join(
            f"{k}={printable(v, 21) if len(v) > 24 else printable(v, 24)}"
            for k, v in list(fields.items())[:TABLE_FIELDS]
        )
        if len(fields) > TABLE_FIELDS:  # the rest: --json, or echo --field
            shown += f" (+{len(fields) - TABLE_FIELDS} more)"
        print(
            f"{format_ns(e.timestamp_ns):<28} {e.timestamp_ns:>20}  {kind:<10}"
            f" {format_bytes(len(e.payload)):>10}  {shown}"
        )
    print(counted(len(elements), "element"))


def _save_all(directory: Path, elements: list[DataObject], force: bool) -> dict[int, list[str]]:
    """Write each element as <timestamp_ns>.png|.bin plus <timestamp_ns>.xml.

    Files are created exclusively and never through a link (``_files``); ``force`` replaces
    existing regular files of the same names.
    """
    from services.tools.bag import frame_layout  # imported here: only --save needs it

    dir_fd = open_directory(directory)
    saved: dict[int, list[str]] = {}
    try:
        for element in elements:
            layout = frame_layout(element.metadata, len(element.payload))
            if layout is not None:
                name, content = f"{element.timestamp_ns}.png", _png(element.payload, layout)
            else:
                name, content = f"{element.timestamp_ns}.bin", element.payload
            names = [name, f"{element.timestamp_ns}.xml"]
            for file_name, data in zip(names, (content, element.metadata), strict=True):
                shown = str(directory / file_name)
                with create_file(file_name, overwrite=force, dir_fd=dir_fd, shown=shown) as out:
                    try:
                        out.write(data)
                    except OSError as exc:
                        raise OutputError(f"cannot write {shown}: {exc.strerror}") from exc
            saved[element.timestamp_ns] = [str(directory / n) for n in names]
    finally:
        os.close(dir_fd)
    return saved


def _png(payload: bytes, layout: Any) -> bytes:
    """The frame as a lossless PNG: gray, colour or colour with alpha as it came."""
    import cv2  # imported here: OpenCV is slow to load and only PNGs need it

    from services.lib.frame_pixels import frame_array, opencv_order

    image = opencv_order(frame_array(payload, layout), layout.encoding)  # OpenCV writes BGR(A)
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise OutputError("cannot encode a frame as PNG: OpenCV refused the image")
    return bytes(encoded)
