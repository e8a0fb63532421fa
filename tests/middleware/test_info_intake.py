"""``InfoIntake``: what of one ``@info/*`` query's replies is kept, decoded, or counted."""

from __future__ import annotations

from middleware._info_intake import (
    _REMEMBERED,
    MAX_DESCRIPTION_BYTES,
    MAX_DESCRIPTIONS,
    TOKENLESS_BYTES,
    InfoIntake,
)


class _Payload:
    """A payload of ``size`` bytes that counts its copies."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.copies = 0

    def __len__(self) -> int:
        return self.size

    def to_bytes(self) -> bytes:
        self.copies += 1
        return b"x" * self.size


def _taken(intake: InfoIntake) -> list[str]:
    intake.end()
    names = []
    while (kept := intake.take()) is not None:
        names.append(kept.name)
    return names


def test_kept_bytes_stay_within_the_caps_and_the_rest_is_never_copied() -> None:
    mib = 1 << 20
    live = [f"live{i}" for i in range(10)]
    intake = InfoIntake(float("inf"), live)
    payloads = [_Payload(3 * mib) for _ in range(10)]
    for name, payload in zip(live, payloads, strict=True):
        intake.offer(name, payload, 0)
    tokenless = [_Payload(3 * mib) for _ in range(3)]
    for i, payload in enumerate(tokenless):
        intake.offer(f"fake{i}", payload, 0)
    names = _taken(intake)
    assert len(names) == MAX_DESCRIPTION_BYTES // (3 * mib)  # 5 token holders, no fake
    assert sum(p.copies for p in payloads + tokenless) == len(names)
    assert any("beyond the" in line for line in intake.reasons())


def test_tokenless_replies_take_their_share_and_come_after_token_holders() -> None:
    intake = InfoIntake(float("inf"), ["real"])
    for i in range(MAX_DESCRIPTIONS):
        intake.offer(f"fake{i}", _Payload(TOKENLESS_BYTES // 4), 0)
    intake.offer("real", _Payload(100), 0)
    names = _taken(intake)
    assert names[0] == "real"
    assert len(names) == 1 + 4


def test_nothing_is_decoded_after_the_deadline() -> None:
    now = [0.0]
    intake = InfoIntake(1.0, ["a", "b"], monotonic=lambda: now[0])
    intake.offer("a", _Payload(10), 0)
    intake.offer("b", _Payload(10), 0)
    assert intake.take() is not None
    now[0] = 1.0
    assert intake.take() is None
    intake.offer("c", _Payload(10), 0)  # after the deadline: ignored
    assert any(line.startswith("1 descriptions not decoded") for line in intake.reasons())


def test_a_million_replies_left_out_keep_a_count_and_a_few_names_only() -> None:
    """Every reply over the caps kept its name for the reason line: a peer answering one
    query a million times held a million names (up to 1 KiB each) until the query ended."""
    intake = InfoIntake(float("inf"), [])
    payload = _Payload(1)
    for i in range(100_000):
        intake.offer(f"made-up-{i}", payload, 0)
    (line,) = intake.reasons()
    assert line.startswith("99984 descriptions of services holding no liveliness token"), line
    assert line.endswith("and 99979 more)"), line
    assert len(intake._tokenless.names) == 5


def test_one_session_answering_a_name_again_and_again_takes_one_place() -> None:
    """A rogue session answering ``@info/victim`` 1,000 times filled the caps (64 replies)
    before the real instance's answer came, which a starting service's one-producer-per-name
    check then never read; now each session's first answer for a name is kept, the rest
    counted, and the real answer with its session comes through."""
    intake = InfoIntake(float("inf"), ["victim"])
    garbage = _Payload(10)
    for _ in range(1_000):
        intake.offer("victim", garbage, 0, "rogue")
    intake.offer("victim", _Payload(10), 0, "real")
    intake.end()
    taken = []
    while (kept := intake.take()) is not None:
        taken.append(kept.replier)
    assert taken == ["rogue", "real"]
    assert garbage.copies == 1
    assert any(line.startswith("999 further descriptions") for line in intake.reasons())


def test_the_sessions_remembered_stay_bounded() -> None:
    intake = InfoIntake(float("inf"), [])
    for i in range(100_000):
        intake.offer(f"made-up-{i}", _Payload(1), 0, f"session{i}")
    assert len(intake._answered) == _REMEMBERED


def test_live_names_that_gave_no_description_are_named() -> None:
    intake = InfoIntake(float("inf"), ["a", "b", "quiet"])
    intake.offer("a", _Payload(10), 0, "s1")
    intake.offer("b", _Payload(10), 0, "s2")
    assert _taken(intake) == ["a", "b"]
    (line,) = intake.reasons()
    assert line.startswith("1 live services (holding their liveliness token) gave no"), line
    assert line.endswith("(quiet)"), line


def test_with_every_live_the_intake_ends_once_each_live_name_answered_and_as_long_again() -> None:
    """``services()``: a peer's queryable that never ends the query does not hold it to its
    timeout; a second answer in a live name inside the slack is still taken."""
    now = [0.0]
    intake = InfoIntake(100.0, ["a", "b"], monotonic=lambda: now[0], every_live=True)
    now[0] = 0.5
    intake.offer("a", _Payload(1), 0, "s1")
    now[0] = 1.0
    intake.offer("b", _Payload(1), 0, "s2")  # every live name: 1 s after asking
    now[0] = 1.5
    intake.offer("a", _Payload(1), 0, "peer")  # within as long again: kept
    taken = [kept.name for _ in range(3) if (kept := intake.take()) is not None]
    assert taken == ["a", "b", "a"]
    now[0] = 2.0
    assert intake.take() is None  # ended, not at the deadline (100)
    assert intake.reasons() == []
