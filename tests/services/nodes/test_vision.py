"""The vision runner's per-frame work, its handler loading and its one-line refusals."""

from __future__ import annotations

import argparse
import logging
import subprocess
import sys
import threading
import tracemalloc
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TypedDict

import numpy as np
import pytest

from middleware import ConfigError, SchemaError
from services.lib.messages import frame_metadata, read_detections
from services.lib.quality import Exposure
from services.lib.vision import Box, FrameMeta, Output, ResultKind
from services.nodes._runtime import CallThread
from services.nodes._vision_handler import (
    handler_argument,
    handler_name,
    load_handler,
    result_kind,
)
from services.nodes._vision_step import _MAX_WARNING_KINDS, Encoded, Skipped, VisionStep
from tests.conftest import REPO, child_env, run_framegate
from tests.helpers.timing import scaled
from tests.services.nodes import vision_handlers

LOG = logging.getLogger("test.vision")


def _frame(frame_id: int, image: np.ndarray | None = None) -> tuple[int, bytes, bytes]:
    image = np.full((12, 16), frame_id % 256, np.uint8) if image is None else image
    start_ns = 1_000_000_000 + frame_id * 66_666_667
    metadata = frame_metadata(frame_id, Exposure(start_ns, 30_000_000), image, None)
    return start_ns, image.tobytes(), metadata


def test_a_handler_gets_the_image_and_the_frame_and_its_boxes_are_the_element() -> None:
    seen: list[tuple[tuple[int, ...], FrameMeta]] = []

    def handler(image: np.ndarray, frame: FrameMeta) -> list[Box]:
        seen.append((image.shape, frame))
        return [Box.from_xywh(frame.frame_id, 0, 0, 2, 2)]

    step = VisionStep(handler, ResultKind.DETECTIONS, "mediator/images", LOG)
    stamp, payload, metadata = _frame(5)
    outcome = step.process(stamp, payload, metadata)
    assert isinstance(outcome, Encoded)
    assert read_detections(outcome.metadata) == (5, [5])
    ((shape, frame),) = seen
    assert shape == (12, 16) and frame.frame_id == 5 and frame.timestamp_ns == stamp
    assert frame.encoding == "mono8" and frame.exposure.duration_ns == 30_000_000


@pytest.mark.parametrize(
    ("image", "dtype"),
    [(np.zeros((12, 16, 4), np.uint8), np.uint8), (np.full((12, 16), 4095, np.uint16), np.uint16)],
)
def test_a_handler_gets_four_channel_and_mono16_frames_as_arrays_of_their_shape(
    image: np.ndarray, dtype: type
) -> None:
    seen: list[np.ndarray] = []

    def handler(got: np.ndarray, frame: FrameMeta) -> list[Box]:
        seen.append(got)
        return []

    step = VisionStep(handler, ResultKind.DETECTIONS, "mediator/images", LOG)
    assert isinstance(step.process(*_frame(5, image)), Encoded)
    [got] = seen
    assert got.shape == image.shape and got.dtype == dtype and np.array_equal(got, image)


def test_a_raising_handler_is_a_counted_skip_with_one_warning_per_exception_type(
    caplog: pytest.LogCaptureFixture,
) -> None:
    def handler(image: np.ndarray, frame: FrameMeta) -> list[Box]:
        if frame.frame_id % 3 == 0:
            raise KeyError(frame.frame_id)
        if frame.frame_id % 3 == 1:
            raise ValueError(frame.frame_id)
        return []

    step = VisionStep(handler, ResultKind.DETECTIONS, "in/put", LOG)
    with caplog.at_level(logging.WARNING, logger="test.vision"):
        outcomes = [step.process(*_frame(i)) for i in range(9)]
    assert [type(o).__name__ for o in outcomes] == ["Skipped", "Skipped", "Encoded"] * 3
    assert step.skipped == {"handler-error:KeyError": 3, "handler-error:ValueError": 3}
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 2, warnings
    assert "handler raised KeyError" in warnings[0] and "handler raised ValueError" in warnings[1]


def test_a_handler_error_counted_before_the_bound_on_kinds_keeps_its_own_count(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # Past the bound on distinct kinds, a ValueError seen first was counted
    # handler-error:other: `info` then said it happened once when it kept happening.
    kinds = [type(f"Error{i}", (Exception,), {}) for i in range(_MAX_WARNING_KINDS + 5)]
    raised = [ValueError, *kinds, ValueError, ValueError]

    def handler(image: np.ndarray, frame: FrameMeta) -> list[Box]:
        raise raised[frame.frame_id]()

    step = VisionStep(handler, ResultKind.DETECTIONS, "in/put", LOG)
    with caplog.at_level(logging.WARNING, logger="test.vision"):
        for i in range(len(raised)):
            step.process(*_frame(i))
    assert step.skipped["handler-error:ValueError"] == 3
    # The kinds past the bound share one count and one warning.
    assert step.skipped["handler-error:other"] == len(kinds) - (_MAX_WARNING_KINDS - 1)
    assert len(caplog.records) == _MAX_WARNING_KINDS + 1


@pytest.mark.parametrize("raised", [ValueError("bad"), SystemExit(3)])
def test_a_handler_s_traceback_shows_its_own_frames_only(
    raised: BaseException, caplog: pytest.LogCaptureFixture
) -> None:
    # framegate's own frames (the runner, its stop guard) came first, and only for an
    # Exception: a SystemExit showed a different, shorter traceback.
    def handler(image: np.ndarray, frame: FrameMeta) -> list[Box]:
        raise raised

    thread = CallThread("test-handler")

    def guarded(work: Callable[[], object]) -> object:  # as the service calls it
        return thread.call(work, threading.Event())

    step = VisionStep(handler, ResultKind.DETECTIONS, "in/put", LOG, call=guarded)
    with caplog.at_level(logging.WARNING, logger="test.vision"):
        step.process(*_frame(1))
    thread.close()
    (message,) = [r.getMessage() for r in caplog.records]
    lines = message.splitlines()
    start = lines.index("Traceback (most recent call last):")
    assert __file__ in lines[start + 1] and "in handler" in lines[start + 1], message
    assert "nodes/vision.py" not in message and "_runtime.py" not in message, message
    assert caplog.records[0].exc_info is None  # the text is the whole traceback


class _Unprintable(Exception):
    def __str__(self) -> str:
        raise RuntimeError("this message cannot be printed")


@pytest.mark.parametrize(
    ("raised", "reason"),
    [
        (_Unprintable(), "handler-error:_Unprintable"),
        (SystemExit(3), "handler-error:SystemExit"),
        (KeyboardInterrupt(), "handler-error:KeyboardInterrupt"),
    ],
)
def test_whatever_a_handler_raises_is_one_skipped_frame_never_the_runner_s_end(
    raised: BaseException, reason: str, caplog: pytest.LogCaptureFixture
) -> None:
    def handler(image: np.ndarray, frame: FrameMeta) -> list[Box]:
        if frame.frame_id == 1:
            raise raised
        return []

    step = VisionStep(handler, ResultKind.DETECTIONS, "in/put", LOG)
    with caplog.at_level(logging.WARNING, logger="test.vision"):
        outcomes = [step.process(*_frame(i)) for i in range(3)]
    assert [type(o).__name__ for o in outcomes] == ["Encoded", "Skipped", "Encoded"]
    assert step.skipped == {reason: 1}
    assert len(caplog.records) == 1 and reason.split(":")[1] in caplog.records[0].getMessage()


def test_a_box_label_is_any_integer_type_and_nothing_else() -> None:
    box = Box.from_xywh(np.int64(3), 0, 0, 2, 2, score=np.float32(0.5))
    assert box.label == 3 and type(box.label) is int
    for bad in (True, -1, 1.5, np.float64(2.0), "3"):
        with pytest.raises(SchemaError, match="label must be an int >= 0"):
            Box.from_xywh(bad, 0, 0, 2, 2)  # type: ignore[arg-type]


def test_bad_frames_wrong_results_and_no_results_are_each_counted() -> None:
    results: list[object] = [Output(b"x"), None, [Box(0, ((0, 0),) * 4)]]
    step = VisionStep(lambda image, frame: results.pop(0), ResultKind.DETECTIONS, "a/b", LOG)
    stamp, payload, metadata = _frame(1)
    short = step.process(stamp, payload[:-1], metadata)
    assert isinstance(short, Skipped) and short.reason == "bad-frame"
    assert "payload is 191 bytes" in short.detail
    assert isinstance(step.process(stamp, payload, b"<not xml"), Skipped)
    assert isinstance(step.process(stamp + 1, payload, metadata), Skipped)  # key != metadata
    assert step.process(stamp, payload, metadata).reason == "bad-result"  # type: ignore[union-attr]
    assert step.process(stamp, payload, metadata).reason == "no-result"  # type: ignore[union-attr]
    assert isinstance(step.process(stamp, payload, metadata), Encoded)
    assert step.skipped == {"bad-frame": 3, "bad-result": 1, "no-result": 1}
    assert step.processed == 3


def test_a_generic_handler_stores_its_payload() -> None:
    step = VisionStep(vision_handlers.histogram, ResultKind.GENERIC, "a/b", LOG)
    outcome = step.process(*_frame(9))
    assert isinstance(outcome, Encoded) and len(outcome.payload) == 16 * 4
    assert b"<mean>9.0</mean>" in outcome.metadata


class _Stats(TypedDict):
    mean: float


def test_a_dict_returned_is_a_generic_result_of_those_fields() -> None:
    # "detections where they are boxes, generic otherwise": a dict was a bad-result every
    # frame, its annotation chose a detections buffer.
    def stats(image: np.ndarray, frame: FrameMeta) -> dict[str, float]:
        return {"mean": float(image.mean()), "peak": np.uint8(image.max())}

    def maybe(image: np.ndarray, frame: FrameMeta) -> Mapping[str, int] | None:
        return {"id": frame.frame_id}

    def listed(image: np.ndarray, frame: FrameMeta) -> list[dict[str, float]]:
        return []

    def typed(image: np.ndarray, frame: FrameMeta) -> _Stats:
        return {"mean": 0.0}

    assert result_kind(stats, "auto") is ResultKind.GENERIC
    assert result_kind(maybe, "auto") is ResultKind.GENERIC
    assert result_kind(listed, "auto") is ResultKind.DETECTIONS  # a list: of boxes gone wrong
    assert result_kind(typed, "auto") is ResultKind.GENERIC
    step = VisionStep(stats, result_kind(stats, "auto"), "a/b", LOG)
    outcome = step.process(*_frame(9))
    assert isinstance(outcome, Encoded) and outcome.payload == b""
    assert b"<mean>9.0</mean>" in outcome.metadata and b"<peak>9</peak>" in outcome.metadata
    assert step.skipped == {}


class _Tracker:
    def __call__(self, image: np.ndarray, frame: FrameMeta) -> Output:
        return Output()


def test_the_result_kind_comes_from_the_return_annotation_or_the_flag() -> None:
    assert result_kind(vision_handlers.brightest, "auto") is ResultKind.DETECTIONS
    assert result_kind(vision_handlers.histogram, "auto") is ResultKind.GENERIC
    assert result_kind(_Tracker(), "auto") is ResultKind.GENERIC
    assert result_kind(lambda image, frame: None, "auto") is ResultKind.DETECTIONS
    assert result_kind(vision_handlers.brightest, "generic") is ResultKind.GENERIC


class _Unhashable:
    __hash__ = None  # type: ignore[assignment]

    def __eq__(self, other: object) -> bool:
        raise RuntimeError("compared")


def test_a_return_annotation_of_any_object_leaves_the_kind_to_the_results() -> None:
    # ``-> [Box]`` (a list, not ``list[Box]``) failed the runner's start with a traceback.
    def listed(image: object, frame: object) -> [Box]:  # type: ignore[valid-type]
        return []

    def odd(image: object, frame: object) -> _Unhashable():  # type: ignore[valid-type]
        return []

    assert result_kind(listed, "auto") is ResultKind.DETECTIONS
    assert result_kind(odd, "auto") is ResultKind.DETECTIONS


def test_a_handler_is_loaded_by_name() -> None:
    handler = load_handler("tests.services.nodes.vision_handlers:brightest")
    assert handler is vision_handlers.brightest


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ("no_colon", "must be 'package.module:function'"),
        ("tests.services.nodes.no_such_module:f", "cannot import .*ModuleNotFoundError"),
        ("tests.services.nodes.vision_handlers:missing", "has no 'missing'"),
        (
            "tests.services.nodes.vision_handlers:brightst",
            r"has no 'brightst' \(did you mean 'brightest'\?\)",
        ),
        ("tests.services.nodes.vision_handlers:NOT_A_FUNCTION", "is an int, not a function"),
        (
            "tests.services.nodes.vision_handlers:one_argument",
            r"cannot be called as handler\(image, frame\): too many positional arguments",
        ),
        ("tests.services.nodes.vision_handlers:TakesNothing", "cannot be called as handler"),
    ],
)
def test_a_handler_that_cannot_be_loaded_is_a_config_error(spec: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        load_handler(spec)


def test_a_module_that_raises_while_importing_is_a_config_error(tmp_path: Path) -> None:
    (tmp_path / "broken_vision_module.py").write_text("raise RuntimeError('no camera here')\n")
    sys.path.insert(0, str(tmp_path))
    try:
        with pytest.raises(ConfigError, match="RuntimeError: no camera here"):
            load_handler("broken_vision_module:f")
    finally:
        sys.path.remove(str(tmp_path))


def test_a_module_that_exits_while_importing_is_a_config_error(tmp_path: Path) -> None:
    exits = tmp_path / "exits_on_import.py"
    exits.write_text("import sys\nsys.exit(5)\n")
    with pytest.raises(ConfigError, match=r"called sys.exit\(5\) while it was imported"):
        load_handler(f"{exits}:f")


def test_an_instance_method_is_bound_to_one_instance_of_its_class(tmp_path: Path) -> None:
    """``module:Class.method``: the class is created once, with no arguments, and its
    method bound (a handler keeping a model loads it in ``__init__``)."""
    module = tmp_path / "method_handlers.py"
    module.write_text(
        "class Det:\n"
        "    def __init__(self):\n"
        "        self.calls = 0\n"
        "    def method(self, image, frame):\n"
        "        self.calls += 1\n"
        "        return self.calls\n"
        "    @staticmethod\n"
        "    def plain(image, frame):\n"
        "        return 'static'\n"
        "class Needs:\n"
        "    def __init__(self, model):\n"
        "        pass\n"
        "    def method(self, image, frame):\n"
        "        return None\n"
    )
    handler = load_handler(f"{module}:Det.method")
    assert (handler(None, None), handler(None, None)) == (1, 2)  # type: ignore[arg-type]
    assert load_handler(f"{module}:Det.plain")(None, None) == "static"  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"instance method, and Needs\(\) failed: TypeError"):
        load_handler(f"{module}:Needs.method")


def test_checking_a_method_handler_does_not_create_its_class(tmp_path: Path) -> None:
    """The flag check (``--help``, ``launch --check``, the launcher itself) only resolves the
    name; the runner creates the class once (a model in ``__init__`` is loaded once)."""
    made = tmp_path / "made"
    module = tmp_path / "counted_handlers.py"
    module.write_text(
        "class Det:\n"
        "    def __init__(self):\n"
        f"        open({str(made)!r}, 'a').write('x')\n"
        "    def find(self, image, frame):\n"
        "        return None\n"
    )
    handler_argument(f"{module}:Det.find")
    assert not made.exists()
    load_handler(f"{module}:Det.find")
    assert made.read_text() == "x"


def test_a_class_named_as_the_handler_is_created_once_and_its_instance_called(
    tmp_path: Path,
) -> None:
    """``module:Class`` with ``__call__``: as ``Class.method``, one instance for the run
    (it was refused: "too many positional arguments", the class's own signature)."""
    module = tmp_path / "class_handlers.py"
    module.write_text(
        "class Det:\n"
        "    made = 0\n"
        "    def __init__(self):\n"
        "        Det.made += 1\n"
        "        self.calls = 0\n"
        "    def __call__(self, image, frame):\n"
        "        self.calls += 1\n"
        "        return self.calls\n"
    )
    handler_argument(f"{module}:Det")  # the flag check creates nothing
    handler = load_handler(f"{module}:Det")
    assert (handler(None, None), handler(None, None)) == (1, 2)  # type: ignore[arg-type]
    assert type(handler).made == 1
    assert handler_name(handler) == f"{module}:Det"


def test_a_class_that_cannot_be_created_with_no_arguments_fails_the_flag_check(
    tmp_path: Path,
) -> None:
    """As the runner would fail (and ``launch`` restart it forever), but without creating
    it: ``launch --check`` and ``run vision --handler`` refuse it up front."""
    made = tmp_path / "made"
    module = tmp_path / "needy_handlers.py"
    module.write_text(
        "class Needs:\n"
        "    def __init__(self, model):\n"
        f"        open({str(made)!r}, 'a').write('x')\n"
        "    def method(self, image, frame):\n"
        "        return None\n"
        "    def __call__(self, image, frame):\n"
        "        return None\n"
    )
    failed = r"Needs\(\) failed: TypeError: missing a required argument: 'model'"
    with pytest.raises(argparse.ArgumentTypeError, match=f"instance method, and {failed}"):
        handler_argument(f"{module}:Needs.method")
    with pytest.raises(argparse.ArgumentTypeError, match=f"Needs is a class, and {failed}"):
        handler_argument(f"{module}:Needs")
    assert not made.exists()


def test_launch_check_and_run_vision_refuse_a_class_that_needs_an_argument(
    tmp_path: Path,
) -> None:
    (tmp_path / "h.py").write_text(
        "class NeedsArg:\n"
        "    def __init__(self, x):\n"
        "        pass\n"
        "    def method(self, image, frame):\n"
        "        return None\n"
    )
    deploy = tmp_path / "vision.yaml"
    deploy.write_text(
        "version: 1\nservices:\n  vision:\n    args:\n      handler: h.py:NeedsArg.method\n"
    )
    checked = _framegate("launch", str(deploy), "--check", cwd=tmp_path)
    assert checked.returncode == 1, checked
    assert f"{deploy}:5" in checked.stderr and "NeedsArg() failed" in checked.stderr, checked
    ran = _framegate("run", "vision", "--handler", "h.py:NeedsArg.method", cwd=tmp_path)
    assert ran.returncode == 1, ran
    assert ran.stderr.startswith(
        "error: framegate run vision: argument --handler: handler 'h.py:NeedsArg.method'"
    ), ran.stderr


def test_run_vision_words_a_class_that_fails_as_it_is_created_as_the_flag_check(
    tmp_path: Path,
) -> None:
    (tmp_path / "h.py").write_text(
        "class Boom:\n"
        "    def __init__(self):\n"
        "        raise RuntimeError('no model file')\n"
        "    def method(self, image, frame):\n"
        "        return None\n"
    )
    ran = _framegate("run", "vision", "--handler", "h.py:Boom.method", cwd=tmp_path)
    assert ran.returncode == 1, ran
    assert ran.stderr.strip().splitlines() == [
        "error: framegate run vision: argument --handler: handler 'h.py:Boom.method': "
        "'method' is an instance method, and Boom() failed: RuntimeError: no model file"
    ], ran.stderr


def test_a_return_annotation_only_a_type_checker_can_resolve_is_read_as_text(
    tmp_path: Path,
) -> None:
    module = tmp_path / "checked_handlers.py"
    module.write_text(
        "from __future__ import annotations\n"
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n"
        "    from services.lib.vision import Output\n"
        "def summary(image, frame) -> Output | None:\n"
        "    return None\n"
        "def boxes(image, frame) -> list[Box]:\n"
        "    return []\n"
    )
    assert result_kind(load_handler(f"{module}:summary"), "auto") is ResultKind.GENERIC
    assert result_kind(load_handler(f"{module}:boxes"), "auto") is ResultKind.DETECTIONS


def _framegate(*argv: str, cwd: Path = REPO) -> subprocess.CompletedProcess[str]:
    return run_framegate(*argv, cwd=cwd, timeout_s=120)


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--handler", "nosuch.module:fn"], "cannot import 'nosuch.module'"),
        (["--handler", "tests.services.nodes.vision_handlers:NOT_A_FUNCTION"], "not a function"),
        ([], "the following arguments are required: --handler"),
        (
            ["--handler", "examples.vision_templat:find_marker"],
            "(did you mean 'examples.vision_template'?)",
        ),
        (["--handler", "tests.services.nodes.vision_handlers:coroutine"], "is an async function"),
    ],
)
def test_run_vision_refuses_a_bad_handler_in_one_line(argv: list[str], says: str) -> None:
    result = _framegate("run", "vision", *argv)
    assert result.returncode == 1, result
    assert result.stderr.startswith("error: ") and says in result.stderr, result
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr


def test_launch_check_imports_the_handler_module_in_a_child_not_in_the_launcher(
    tmp_path: Path,
) -> None:
    """What a module does as it is imported (a model at module level, a GPU context) must
    not stay in the launcher for its whole life: measured, a 200 MB module-level array
    made the launcher 278 MB. The module notes each process that imports it."""
    pids = tmp_path / "pids"
    (tmp_path / "noted.py").write_text(
        "import os\n"
        f"open({str(pids)!r}, 'a').write(f'{{os.getpid()}} {{os.getppid()}}\\n')\n"
        "def fn(image, frame):\n"
        "    return None\n"
    )
    deploy = tmp_path / "vision.yaml"
    deploy.write_text("version: 1\nservices:\n  vision:\n    args:\n      handler: noted.py:fn\n")
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "launch", str(deploy), "--check"],
        cwd=tmp_path,
        env=child_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    out, err = proc.communicate(timeout=scaled(120))
    assert proc.returncode == 0, (out, err)
    imports = [tuple(map(int, line.split())) for line in pids.read_text().splitlines()]
    assert imports, "the handler was not checked"
    assert all(pid != proc.pid and parent == proc.pid for pid, parent in imports), imports


def test_launch_check_names_the_deploy_line_of_a_bad_handler(tmp_path: Path) -> None:
    deploy = tmp_path / "vision.yaml"
    deploy.write_text(
        "version: 1\nservices:\n  vision:\n    args:\n      handler: nosuch.module:fn\n"
    )
    result = _framegate("launch", str(deploy), "--check")
    assert result.returncode == 1, result
    assert f"{deploy}:5" in result.stderr and "cannot import 'nosuch.module'" in result.stderr


def test_launch_check_refuses_a_runner_without_a_handler_in_one_line(tmp_path: Path) -> None:
    deploy = tmp_path / "vision.yaml"
    deploy.write_text("version: 1\nservices:\n  vision:\n    args: {queue: 2}\n")
    result = _framegate("launch", str(deploy), "--check")
    assert result.returncode == 1, result
    assert result.stderr.strip().splitlines() == [
        f"error: {deploy}: service 'vision': the following arguments are required: --handler"
        " (see 'framegate run vision --help')"
    ], result.stderr


def test_a_handler_is_loaded_from_a_file_with_its_siblings_importable(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(sys, "path", list(sys.path))  # the file's directory is added
    (tmp_path / "helper_of_json_py.py").write_text("LABEL = 7\n")
    # Named like a standard module on purpose: the file is loaded, not the library.
    (tmp_path / "json.py").write_text(
        "from helper_of_json_py import LABEL\n"
        "LOADS = []\n"
        "LOADS.append(1)\n"
        "def find(image, frame):\n"
        "    return LABEL\n"
    )
    spec = f"{tmp_path / 'json.py'}:find"
    handler = load_handler(spec)
    assert handler(np.zeros((1, 1), np.uint8), None) == 7  # type: ignore[arg-type]
    assert load_handler(spec) is handler
    assert handler_name(handler) == f"{tmp_path / 'json.py'}:find"  # not its private module
    assert sys.modules[handler.__module__].LOADS == [1]  # loaded once for both
    with pytest.raises(ConfigError, match="does not exist"):
        load_handler(f"{tmp_path / 'missing.py'}:find")


@pytest.mark.parametrize(
    "fields",
    [{"x": np.zeros(10**6)}, {"x": list(range(10**6))}, {"x": "a" * 10**6}, {"y" * 10**6: 1}],
    ids=["array", "list", "text", "name"],
)
def test_a_result_whose_fields_cannot_fit_the_metadata_is_refused_before_it_is_written(
    fields: dict[str, object],
) -> None:
    """Fields of a million values were turned into megabytes of XML (half a gigabyte and a
    minute of the runner's thread at 10^7) before the metadata's size limit refused them."""
    output = Output(b"", fields)
    step = VisionStep(lambda image, frame: output, ResultKind.GENERIC, "a/b", LOG)
    tracemalloc.start()
    try:
        outcome = step.process(*_frame(1))
        peak_bytes = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert isinstance(outcome, Skipped) and outcome.reason == "bad-result"
    assert "over the limit of 65536 bytes" in outcome.detail
    assert peak_bytes < 4 * 2**20
    assert step.skipped == {"bad-result": 1}


def test_boxes_whose_metadata_cannot_fit_are_a_bad_result_naming_them() -> None:
    """Fewer than 1,000 boxes may still be more than the metadata's 64 KiB hold: counted
    ``bad-result`` saying so, not an element every buffer refuses at ``put``."""
    boxes = [Box.from_xywh(123_456, 1234.5678901, 2345.678901, 10.1234567, 20.9876543)] * 500
    step = VisionStep(lambda image, frame: boxes, ResultKind.DETECTIONS, "a/b", LOG)
    outcome = step.process(*_frame(1))
    assert isinstance(outcome, Skipped) and outcome.reason == "bad-result"
    assert "for 500 boxes" in outcome.detail


class _ExitsWhenPrinted:
    def __str__(self) -> str:
        raise SystemExit(3)


def test_a_result_whose_conversion_exits_is_a_bad_result_never_the_runner_s_end() -> None:
    # The result was written as metadata on the runner's own thread, outside the guard
    # around the handler: a field's __str__ raising SystemExit ended the runner.
    results: list[object] = [Output(fields={"x": _ExitsWhenPrinted()}), Output(b"ok")]
    step = VisionStep(lambda image, frame: results.pop(0), ResultKind.GENERIC, "a/b", LOG)
    outcomes = [step.process(*_frame(i)) for i in range(2)]
    assert [type(o).__name__ for o in outcomes] == ["Skipped", "Encoded"]
    assert step.skipped == {"bad-result": 1}


class _StopInTest(BaseException):
    pass


def _processing_in_a_thread(
    handler: Callable[[np.ndarray, FrameMeta], list[Box]],
    thread: CallThread,
    stop: threading.Event,
) -> tuple[threading.Thread, list[BaseException]]:
    """A step calling ``handler`` through ``thread`` as the service does (a stop ends the
    call), and a thread (not started) that processes one frame with it; the list gets the
    stop's exception when the step ends by the stop."""

    def guarded(work: Callable[[], object]) -> object:
        result = thread.call(work, stop)
        if result is None:
            raise _StopInTest
        return result

    step = VisionStep(handler, ResultKind.DETECTIONS, "in/put", LOG, call=guarded)
    ended: list[BaseException] = []

    def process() -> None:
        try:
            step.process(*_frame(1))
        except _StopInTest as exc:
            ended.append(exc)

    return threading.Thread(target=process, daemon=True), ended


def test_a_stop_reaches_a_result_whose_conversion_never_returns() -> None:
    # A box corner's __float__ (or a field's __str__) that blocks ran on the loop's thread,
    # where a stop cannot reach it: SIGTERM left the runner hanging for good.
    entered, release = threading.Event(), threading.Event()

    class Stuck(float):
        def __float__(self) -> float:
            entered.set()
            release.wait()
            return 0.0

    def handler(image: np.ndarray, frame: FrameMeta) -> list[Box]:
        return [Box(1, ((Stuck(0.0), 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)))]

    thread, stop = CallThread("test-handler"), threading.Event()
    worker, ended = _processing_in_a_thread(handler, thread, stop)
    try:
        # Box's own check converts the corners once, the result's writing again.
        worker.start()
        assert entered.wait(scaled(10))
        entered.clear()
        release.set()
        release.clear()
        assert entered.wait(scaled(10))
        stop.set()
        worker.join(scaled(10))
        assert not worker.is_alive() and ended
    finally:
        release.set()
        thread.close()


class _ExitsWhenSaid(Exception):
    def __str__(self) -> str:
        raise SystemExit(3)


def test_an_exception_whose_message_exits_is_one_skipped_frame() -> None:
    # Its message was read on the runner's loop, to be logged: SystemExit ended the runner.
    def handler(image: np.ndarray, frame: FrameMeta) -> list[Box]:
        if frame.frame_id == 1:
            raise _ExitsWhenSaid
        return []

    step = VisionStep(handler, ResultKind.DETECTIONS, "in/put", LOG)
    outcomes = [step.process(*_frame(i)) for i in range(3)]
    assert [type(o).__name__ for o in outcomes] == ["Encoded", "Skipped", "Encoded"]
    assert step.skipped == {"handler-error:_ExitsWhenSaid": 1}


def test_a_stop_reaches_an_exception_whose_message_never_returns() -> None:
    entered, release = threading.Event(), threading.Event()

    class Stuck(Exception):
        def __str__(self) -> str:
            entered.set()
            release.wait()
            return "stuck"

    def handler(image: np.ndarray, frame: FrameMeta) -> list[Box]:
        raise Stuck

    thread, stop = CallThread("test-handler"), threading.Event()
    worker, ended = _processing_in_a_thread(handler, thread, stop)
    try:
        worker.start()
        assert entered.wait(scaled(10))
        stop.set()
        worker.join(scaled(10))
        assert not worker.is_alive() and ended
    finally:
        release.set()
        thread.close()
