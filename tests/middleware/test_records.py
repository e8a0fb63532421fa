"""The hot-path record builders give exactly the records their constructors give."""

from __future__ import annotations

import dataclasses
import inspect

from middleware._records import DataObject, Notification, data_object, notification


def test_builders_set_every_field_of_their_record() -> None:
    """A field added to a record without its builder fails here, not in a consumer."""
    for record, builder in ((DataObject, data_object), (Notification, notification)):
        fields = [f.name for f in dataclasses.fields(record)]
        params = [p for p in inspect.signature(builder).parameters if not p.startswith("_")]
        assert params == fields, record.__name__


def test_builders_equal_the_constructors() -> None:
    element = data_object(7, b"payload", b"<m/>")
    assert element == DataObject(7, b"payload", b"<m/>")
    assert type(element) is DataObject
    assert hash(element) == hash(DataObject(7, b"payload", b"<m/>"))
    note = notification("svc", "buf", 7, 3, b"<m/>", element, 1, "P.1")
    assert note == Notification("svc", "buf", 7, 3, b"<m/>", element, 1, "P.1")
    assert repr(note) == repr(Notification("svc", "buf", 7, 3, b"<m/>", element, 1, "P.1"))
