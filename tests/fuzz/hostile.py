"""Generators of hostile input for a live framegate service (seeded, reproducible)."""

from __future__ import annotations

import random
import string

import msgpack

NS = 'xmlns="urn:framegate:1"'
_TIME_ATOMS = [
    "now()",
    "now(-2s)",
    "now(5m)",
    "now(-1.5h)",
    "now(-)",
    "now(2q)",
    "now(",
    "now())",
    "2026-11-22T14:00:00Z",
    "2026-11-22T14:00:00.123456789Z",
    "2026-02-30T00:00:00Z",
    "2026-11-22T14:00:00+25:00",
    "0",
    "-1",
    "9" * 30,
    "1e9",
    "",
    " ",
    "..",
    ";",
    "[",
    "]",
    "\u00e9",
    "\x00",
    "NaN",
    "inf",
    "1.5ms",
]


def _junk(rng: random.Random, n: int) -> str:
    alphabet = string.printable + "\u00e9\u4e2d\U0001f600[]..;=&?#*$@/"
    return "".join(rng.choice(alphabet) for _ in range(rng.randint(0, n)))


def time_range(rng: random.Random) -> str:
    """A _time value: mostly grammar-shaped, sometimes junk."""
    if rng.random() < 0.2:
        return _junk(rng, 30)
    left, right = rng.choice("[]"), rng.choice("[]")
    a, b = rng.choice(_TIME_ATOMS), rng.choice(_TIME_ATOMS)
    sep = rng.choice(["..", ";", "...", "", ".."])
    if sep == ";":
        b = rng.choice(["2s", "-1s", "5", "1x", "0.5ms", ""])
    return f"{left}{a}{sep}{b}{right}"


def query_parameters(rng: random.Random) -> dict[str, str]:
    """Selector parameters a data query might carry, hostile or not."""
    params: dict[str, str] = {}
    for _ in range(rng.randint(0, 3)):
        key = rng.choice(["_time", "last", "at", "ts", "limit", "_anyke", _junk(rng, 6)])
        if key == "_time":
            params[key] = time_range(rng)
        elif key in ("last", "at", "ts"):
            params[key] = rng.choice(
                [str(rng.randint(-5, 10**6)), "x", "", "1.5", "9" * 40, "-0", _junk(rng, 5)]
            )
        else:
            params[key] = _junk(rng, 10)
    # Keys and values with ';' or '=' inside would split the selector; Zenoh does not escape.
    return {k: v for k, v in params.items() if k and not set(k + v) & set(";=&#?\x00")}


def metadata(rng: random.Random, timestamp_ns: int) -> tuple[bytes, bool]:
    """A metadata document and whether a correct service must accept it."""
    t = timestamp_ns
    choice = rng.randrange(14)
    if choice == 0:
        return f'<metadata {NS} kind="generic" timestamp_ns="{t}"/>'.encode(), True
    if choice == 1:
        return (
            f'<?xml version="1.0"?><!DOCTYPE m [<!ENTITY x SYSTEM "file:///etc/passwd">]>'
            f'<metadata {NS} kind="generic" timestamp_ns="{t}">&x;</metadata>'
        ).encode(), False
    if choice == 2:
        depth = rng.randint(2, 12)
        ents = '<!ENTITY l0 "lol">' + "".join(
            f'<!ENTITY l{i} "{("&l" + str(i - 1) + ";") * 10}">' for i in range(1, depth)
        )
        return (
            f"<!DOCTYPE b [{ents}]><metadata {NS} kind='generic' "
            f"timestamp_ns='{t}'>&l{depth - 1};</metadata>"
        ).encode(), False
    if choice == 3:
        depth = rng.choice([33, 100, 1000, 5000])
        body = "<a>" * depth + "</a>" * depth
        return f"<metadata {NS} kind='generic' timestamp_ns='{t}'>{body}</metadata>".encode(), False
    if choice == 4:
        size = rng.choice([70_000, 500_000, 2_000_000])
        return (
            f"<metadata {NS} kind='generic' timestamp_ns='{t}' x='{'a' * size}'/>".encode(),
            False,
        )
    if choice == 5:
        ns = rng.choice(['xmlns="urn:other"', "", 'xmlns="urn:framegate:2"'])
        return f"<metadata {ns} kind='generic' timestamp_ns='{t}'/>".encode(), False
    if choice == 6:
        return b"<metadata " + bytes(rng.randrange(256) for _ in range(40)) + b"/>", False
    if choice == 7:
        return bytes(rng.randrange(256) for _ in range(rng.randint(0, 200))), False
    if choice == 8:
        return f"<metadata {NS} kind='frame' timestamp_ns='{t}'/>".encode(), False
    if choice == 9:
        return f"<metadata {NS} kind='generic' timestamp_ns='{t + 1}'/>".encode(), False
    if choice == 10:
        return f"<metadata {NS} kind='generic'/>".encode(), False
    if choice == 11:
        body = "<x><![CDATA[x]]></x><!-- c -->"
        doc = f"<metadata {NS} kind='generic' timestamp_ns='{t}'>{body}</metadata>"
        return doc.encode(), True
    if choice == 12:
        doc = f"<metadata {NS} kind='generic' timestamp_ns='{t}'><x>\u00e9\u4e2d</x></metadata>"
        return doc.encode(), True
    return f"<metadata {NS} kind='nope' timestamp_ns='{t}'/>".encode(), False


def control_message(rng: random.Random) -> bytes:
    """Garbage for notification and ack keys: random bytes or wrong-typed msgpack."""
    choice = rng.randrange(5)
    if choice == 0:
        return bytes(rng.randrange(256) for _ in range(rng.randint(0, 64)))
    if choice == 1:
        return bytes(msgpack.packb({"e": rng.choice([1, None, "x", b"y"]), "s": "seq"}))
    if choice == 2:
        return bytes(msgpack.packb({"e": "deadbeef", "s": rng.choice([-1, 10**12, 2**63 - 1])}))
    if choice == 3:
        return bytes(msgpack.packb([1, 2, 3]))
    return bytes(msgpack.packb({"e": "x", "s": 1, "t": "now", "p": 5, "m": [1]}))


def token_suffix(rng: random.Random) -> tuple[str, bool]:
    """``<mode>/<N>/<push>`` for a subscription token (the full four-segment shape the
    producer's token parser sees) and whether a correct producer must register it."""
    mode = rng.choice(["flow", "observe", "observe", "bogus", "FLOW", "-"])
    size = rng.choice(["1", "4", "0", "-1", "x", "1e3", "99999999999", "2"])
    push = rng.choice(["-1", "0", "65536", "-2", "y", "1.5"])
    valid = (
        mode in ("flow", "observe")
        and size.isdigit()
        and 1 <= int(size) <= 1 << 20
        and push.lstrip("-").isdigit()
        and int(push) >= -1
    )
    return f"{mode}/{size}/{push}", valid


def forged_notification(rng: random.Random, epoch: str | None, descriptor: str) -> bytes:
    """A protocol-valid notification header (README "Wire format"): a foreign epoch with
    any seq, or the real epoch with a past (1) or far-future seq, maybe another
    registration's descriptor. (An in-window seq of the real epoch is indistinguishable
    from the producer's own: outside the trusted profile's promise.)"""
    if epoch is not None and rng.random() < 0.6:
        seq = rng.choice([1, rng.randint(10**6, 2**40)])
    else:
        epoch, seq = rng.choice(["x", "0.1", "ffff.1"]), rng.choice([1, 2, rng.randint(1, 99)])
    body: list[object] = [  # epoch, seq, timestamp_ns, metadata, pushed, acked, descriptor
        epoch,
        seq,
        2 * rng.randint(0, 2**40) + 1,  # odd: never one of the fuzzer's own timestamps
        f'<metadata {NS} kind="generic" timestamp_ns="1"/>'.encode(),
        rng.random() < 0.5,
        None,
        None,
    ]
    if rng.random() < 0.5:
        body[6] = descriptor if rng.random() < 0.5 else "observe/1/-1"
    return bytes(msgpack.packb(body, use_bin_type=True))


def forged_ack(rng: random.Random, epoch: str | None) -> bytes:
    """A protocol-valid ack of a foreign epoch, or of the real one with a past seq (an
    in-window forged ack of a live epoch is outside the trusted profile's promise)."""
    if epoch is None or rng.random() < 0.5:
        foreign = rng.choice(["x", "0.1", "ffff.1"])
        return bytes(msgpack.packb({"e": foreign, "s": rng.randint(0, 99)}))
    return bytes(msgpack.packb({"e": epoch, "s": 0}))
