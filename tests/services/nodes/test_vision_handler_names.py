"""A handler named wrongly is refused at start with the name to write, and one that could
never give a result (``async def``, a generator) is refused at start, not counted per frame."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import pytest

from middleware import ConfigError
from services.lib.messages import frame_metadata
from services.lib.quality import Exposure
from services.lib.vision import FrameMeta, ResultKind
from services.nodes._vision_handler import load_handler
from services.nodes._vision_step import Skipped, VisionStep

LOG = logging.getLogger("test.vision.names")


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        # A misspelt module of the handler's own name, at any depth of it.
        (
            "examples.vision_templat:find_marker",
            r"\(did you mean 'examples.vision_template'\?\)",
        ),
        ("exampls.vision_template:find_marker", r"\(did you mean 'examples.vision_template'\?\)"),
        # A path where a module name goes, without its .py.
        (
            "examples/vision_template:find_marker",
            r"\(did you mean 'examples/vision_template.py:find_marker'\?\)",
        ),
        # A module name written as a file.
        (
            "examples.vision_template.py:find_marker",
            r"does not exist \(did you mean 'examples/vision_template.py'\?\)",
        ),
        ("examples/vision_templat.py:find_marker", r"\(did you mean 'examples/vision_template.py'"),
        # ``Class.method`` misspelt: the whole name to write, not only its last part.
        ("services.lib.vision:Box.from_xyw", r"\(did you mean 'Box.from_xywh'\?\)"),
    ],
)
def test_a_misspelt_handler_name_gets_the_name_to_write(spec: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        load_handler(spec)


def test_a_top_level_module_is_guessed_only_among_the_users_own(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """From another directory, a module of one's own is not importable: the error says how
    to make it so, and never guesses among the standard library's names (``examples`` was
    read as ``tempfile``); a misspelt module of the current directory is guessed."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match="run from there, add it to PYTHONPATH") as raised:
        load_handler("mypkg_not_here.detect:find")
    assert "did you mean" not in str(raised.value)
    (tmp_path / "my_detector.py").write_text("def find(image, frame):\n    return []\n")
    with pytest.raises(ConfigError, match=r"\(did you mean 'my_detector'\?\)"):
        load_handler("my_detectr:find")


def test_a_module_the_handlers_module_imports_is_not_guessed_at(tmp_path: Path) -> None:
    """A missing dependency is the user's to install: no did-you-mean for it."""
    module = tmp_path / "needs_a_framework.py"
    module.write_text("import numpyy\n\ndef find(image, frame):\n    return []\n")
    with pytest.raises(ConfigError, match="No module named 'numpyy'") as raised:
        load_handler(f"{module}:find")
    assert "did you mean" not in str(raised.value)


def test_a_handler_file_that_fails_to_import_is_not_told_to_add_its_py(tmp_path: Path) -> None:
    """A file named with its .py that raised (a SyntaxError) got the hint for a path written
    without it: `(a handler file is named with its .py: 'path/to/file.py:find')`."""
    module = tmp_path / "broken.py"
    module.write_text("def find(image, frame:\n    return []\n")
    with pytest.raises(ConfigError, match=r"SyntaxError: .*\(broken\.py, line 1\)$"):
        load_handler(f"{module}:find")


@pytest.mark.parametrize(
    ("name", "match"),
    [
        ("find", "is an async function: .* define it with 'def'"),
        ("Det.find", "is an async function"),
        ("Det", "is an async function"),
        ("each", r"is a generator function \(it yields\)"),
    ],
)
def test_a_handler_that_returns_no_result_but_a_coroutine_is_refused_at_start(
    tmp_path: Path, name: str, match: str
) -> None:
    """An ``async def`` handler returned a coroutine for every frame: a per-frame
    ``bad-result`` whose words ("annotate it '-> Output'") led away from the cause, and a
    "coroutine was never awaited" warning."""
    module = tmp_path / "async_handlers.py"
    module.write_text(
        "async def find(image, frame):\n"
        "    return []\n"
        "def each(image, frame):\n"
        "    yield []\n"
        "class Det:\n"
        "    async def find(self, image, frame):\n"
        "        return []\n"
        "    async def __call__(self, image, frame):\n"
        "        return []\n"
    )
    with pytest.raises(ConfigError, match=match):
        load_handler(f"{module}:{name}")


def test_an_exception_type_of_any_name_is_a_skip_reason_info_can_show() -> None:
    """A type made at run time may be named with a newline or at any length; its skip
    reason made the results buffer's description unreadable (``framegate info`` said "a key
    holds an unprintable character (U+000A)")."""
    odd = type("Bad\nName", (Exception,), {})
    long = type("E" * 5000, (Exception,), {})
    raised = iter([odd("x"), long("y")])

    def handler(image: np.ndarray, frame: FrameMeta) -> None:
        raise next(raised)

    step = VisionStep(handler, ResultKind.DETECTIONS, "in/put", LOG)
    image = np.zeros((4, 4), np.uint8)
    reasons = []
    for n in range(2):
        stamp = 1_000_000_000 + n
        metadata = frame_metadata(n, Exposure(stamp, 1_000_000), image, None)
        outcome = step.process(stamp, image.tobytes(), metadata)
        assert isinstance(outcome, Skipped)
        reasons.append(outcome.reason)
    assert reasons == ["handler-error:Bad?Name", "handler-error:" + "E" * 64]


_LOOKED_AT = """
class Attributes:
    def __getattr__(self, name):
        raise RuntimeError("no attributes here")

    def __call__(self, image, frame):
        return []


class Lies:
    @property
    def __class__(self):
        raise RuntimeError("class lookup")

    def __call__(self, image, frame):
        return []


class Signature:
    @property
    def __signature__(self):
        raise RuntimeError("signature")

    def __call__(self, image, frame):
        return []


attributes, lies, signature = Attributes(), Lies(), Signature()
"""


@pytest.mark.parametrize(
    ("name", "says"),
    [
        ("attributes.find", "RuntimeError: no attributes here"),
        ("attributes", "RuntimeError: no attributes here"),
        ("lies", "RuntimeError: class lookup"),
        ("signature", "RuntimeError: signature"),
    ],
)
def test_a_handler_object_that_raises_as_it_is_looked_at_is_a_config_error(
    tmp_path: Path, name: str, says: str
) -> None:
    # Its own code runs as it is looked up and checked: a traceback, not one error line.
    module = tmp_path / "looked_at.py"
    module.write_text(_LOOKED_AT)
    with pytest.raises(ConfigError, match=f"handler '.*:{name}': looking up .* raised {says}"):
        load_handler(f"{module}:{name}", bind=False)


def test_a_handler_object_is_named_in_the_log_whatever_its_getattr_raises() -> None:
    from services.nodes._vision_handler import handler_name

    class Model:  # delegates to a model that raises for names it lacks
        def __getattr__(self, name: str) -> object:
            if name == "__wrapped__":
                raise AttributeError(name)
            raise RuntimeError(f"model has no {name}")

        def __call__(self, image: object, frame: object) -> list[object]:
            return []

    assert handler_name(Model()).endswith(".<locals>.Model")


def test_a_package_file_named_by_path_is_told_its_module_name(tmp_path: Path) -> None:
    # Loaded by path, a file has no package: its relative imports fail.
    package = tmp_path / "mypkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "util.py").write_text("def g():\n    return []\n")
    (package / "handler.py").write_text(
        "from .util import g\n\ndef f(image, frame):\n    return g()\n"
    )
    with pytest.raises(
        ConfigError,
        match=rf"name it 'mypkg.handler:f' and run from '{re.escape(str(tmp_path))}' ",
    ):
        load_handler(f"{package / 'handler.py'}:f", bind=False)
