"""XSD schemas of every framegate metadata kind, shipped as package data.

``schemas/<kind>.xsd`` checks a document whose root is ``<metadata kind="<kind>">`` in the
namespace ``urn:framegate:1``; ``envelope.xsd`` is checked first for every kind.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["NAMESPACE", "SCHEMA_DIR", "kinds"]

NAMESPACE = "urn:framegate:1"
SCHEMA_DIR = Path(__file__).resolve().parent

# Files that are building blocks, not metadata kinds.
_NOT_KINDS = {"common", "envelope"}


def kinds() -> list[str]:
    """Names of the metadata kinds that have an XSD here, sorted."""
    return sorted(p.stem for p in SCHEMA_DIR.glob("*.xsd") if p.stem not in _NOT_KINDS)
