"""The exception tree drawn in ``middleware/_errors.py`` is the whole tree."""

from __future__ import annotations

import importlib

import middleware
from middleware import FramegateError
from tests.test_architecture import MODULES


def _all_subclasses(cls: type) -> set[type]:
    found = set(cls.__subclasses__())
    for sub in list(found):
        found |= _all_subclasses(sub)
    return found


def test_every_framegate_error_is_drawn_in_the_one_docstring() -> None:
    for name in MODULES:
        if not name.endswith("__main__"):
            importlib.import_module(name)
    drawing = importlib.import_module("middleware._errors").__doc__ or ""
    ours = {c for c in _all_subclasses(FramegateError) if c.__module__.split(".")[0] != "tests"}
    missing = sorted(c.__name__ for c in ours if f" {c.__name__} " not in drawing)
    assert missing == [], f"add {missing} to the tree in middleware/_errors.py"


def test_middleware_exports_only_its_own_errors() -> None:
    exported = [getattr(middleware, n) for n in middleware.__all__]
    errors = [e for e in exported if isinstance(e, type) and issubclass(e, FramegateError)]
    assert all(e.__module__ == "middleware._errors" for e in errors)
