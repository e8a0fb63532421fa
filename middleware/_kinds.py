"""Metadata kinds of an application's own: an XSD registered at run time."""

from __future__ import annotations

import re
from pathlib import Path

import schemas

from ._errors import ConfigError, SchemaError

_KIND = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")


def register_kind(kind: str, xsd: str | Path) -> None:
    """Make ``kind`` a metadata kind checked by the XSD file ``xsd`` in this process.

    The XSD must declare ``<metadata>`` in the namespace ``urn:framegate:1`` (the envelope's
    rules on ``kind`` and ``timestamp_ns`` are checked before it). Register before the first
    ``offer`` of that kind, in every process that offers it. A shipped kind cannot be
    replaced; registering the same file again is harmless.
    """
    if not _KIND.match(kind):
        raise ConfigError(f"bad metadata kind {kind!r}: use letters, digits and '_'")
    path = Path(xsd).resolve()
    known = schemas.schema_path(kind)
    if known.resolve() == path:
        return
    if known.is_file():
        raise ConfigError(f"metadata kind {kind!r} is already checked by {known}; pick a new name")
    if not path.is_file():
        raise SchemaError(f"no XSD file at {path} for metadata kind {kind!r}")
    schemas.add_kind(kind, path)
