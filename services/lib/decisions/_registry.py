"""Every policy by name: what ``--policy`` offers. A new policy adds one line here."""

from __future__ import annotations

from collections.abc import Callable

from services.lib.argtypes import did_you_mean
from services.lib.quality import QualityInputError

from ._adaptive import AdaptivePolicy
from ._deadline import DeadlinePolicy
from ._paper import PaperPolicy
from ._policy import Policy
from ._replace import ReplacePolicy

POLICIES: dict[str, Callable[[], Policy]] = {
    "paper": PaperPolicy,
    "replace": ReplacePolicy,
    "deadline": DeadlinePolicy,
    "adaptive": AdaptivePolicy,
}
"""Policy name -> a factory taking no arguments (defaults of a policy's own parameters)."""

DEFAULT_POLICY = "paper"


def make_policy(name: str) -> Policy:
    """A fresh policy of this name (each decider needs its own: policies may keep state)."""
    try:
        factory = POLICIES[name]
    except KeyError:
        known = ", ".join(sorted(POLICIES))
        hint = did_you_mean(name, POLICIES, quote=True)
        raise QualityInputError(f"unknown policy {name!r}{hint}: use one of {known}") from None
    return factory()
