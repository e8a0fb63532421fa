"""A producer's token inbox: a token that came and went between two looks is its
withdrawal alone (no registration, greeting or retirement), and nothing else changes."""

from __future__ import annotations

from middleware._inbox import Control, TokenInbox


def _taken(*events: tuple[str, bool]) -> tuple[list[tuple[str, bool]], int]:
    inbox = TokenInbox(capacity=64, signal=lambda: None)
    for key, alive in events:
        inbox._items.append(Control(key, b"", alive))  # as Zenoh's thread appends them
    return [(c.key, c.alive) for c in inbox.take(64)], inbox.collapsed


def test_a_token_that_came_and_went_in_one_batch_is_its_withdrawal_alone() -> None:
    assert _taken(("a", True), ("a", False)) == ([("a", False)], 1)


def test_a_withdrawal_then_a_new_token_keeps_both() -> None:
    assert _taken(("a", False), ("a", True)) == ([("a", False), ("a", True)], 0)


def test_only_the_puts_a_later_delete_undoes_are_dropped() -> None:
    taken = _taken(("a", True), ("b", True), ("a", False), ("a", True), ("c", False))
    assert taken == ([("b", True), ("a", False), ("a", True), ("c", False)], 1)


def test_a_batch_without_withdrawals_is_untouched() -> None:
    assert _taken(("a", True), ("b", True)) == ([("a", True), ("b", True)], 0)
