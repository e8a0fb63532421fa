"""XSD schemas of every framegate metadata kind, shipped as package data.

``schemas/<kind>.xsd`` checks a document whose root is ``<metadata kind="<kind>">`` in the
namespace ``urn:framegate:1``; ``envelope.xsd`` is checked first for every kind. An
application adds kinds of its own with ``middleware.register_kind``
(``examples/custom_service.py`` shows how).
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["NAMESPACE", "SCHEMA_DIR", "add_kind", "kinds", "schema_path"]

NAMESPACE = "urn:framegate:1"
SCHEMA_DIR = Path(__file__).resolve().parent

# Files that are building blocks, not metadata kinds.
_NOT_KINDS = {"common", "envelope"}

# Kinds an application registered in this process: kind -> its XSD.
_REGISTERED: dict[str, Path] = {}


def kinds() -> list[str]:
    """Names of the metadata kinds known in this process, sorted."""
    shipped = {p.stem for p in SCHEMA_DIR.glob("*.xsd") if p.stem not in _NOT_KINDS}
    return sorted(shipped | set(_REGISTERED))


def add_kind(kind: str, xsd: Path) -> None:
    """Record ``kind``'s XSD; callers check it first (``middleware.register_kind``)."""
    _REGISTERED[kind] = xsd


def schema_path(kind: str) -> Path:
    """The XSD that checks ``kind`` (it may not exist: callers report unknown kinds)."""
    return _REGISTERED.get(kind, SCHEMA_DIR / f"{kind}.xsd")
