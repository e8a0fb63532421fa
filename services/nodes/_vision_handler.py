"""Loading a vision handler by name, and the kind of buffer its results go to.

``framegate run vision --handler SPEC`` names the handler; :func:`handler_argument` loads it
while the flags are parsed, so a bad name is one ``error:`` line before anything starts and
``framegate launch --check`` names the deploy file's line. A launcher checks it in a child
process (:func:`checked_apart`): it runs no handler, and must not hold what a module does as
it is imported (a model loaded at module level, a GPU context, a device) for its whole life.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import importlib.util
import inspect
import os
import pkgutil
import re
import subprocess
import sys
import types
import typing
from collections.abc import Callable, Iterator, Mapping
from contextvars import ContextVar
from pathlib import Path
from types import ModuleType

import numpy as np
import numpy.typing as npt

from middleware import ConfigError
from services.lib.argtypes import closest, did_you_mean
from services.lib.vision import FrameMeta, Output, ResultKind

# What a handler gets (``services.lib.vision`` says which shape for which encoding).
Image = npt.NDArray[np.uint8] | npt.NDArray[np.uint16]
Handler = Callable[[Image, FrameMeta], object]


def load_handler(spec: str, *, bind: bool = True) -> Handler:
    """The callable ``spec`` names: ``package.module:function``, ``module:Class.method``,
    ``module:Class`` (a class with ``__call__``: created once, the instance is called) or
    ``path/to/file.py:function``. ``bind=False``: only check that it names one (a class is
    not created, only checked that it can be with no arguments: the flag check of a launcher
    or ``--check`` must not load a model).

    ConfigError, naming what is wrong, if the module cannot be imported (any exception
    while importing it counts), the name is missing or not callable. The current directory
    is importable, as for ``python -m``; so is a file's own directory (its siblings).
    """
    module_name, sep, attr_path = spec.rpartition(":")
    if not sep or not module_name or not attr_path:
        raise ConfigError(
            f"handler {spec!r} must be 'package.module:function' or 'file.py:function'"
        )
    if os.getcwd() not in sys.path and "" not in sys.path:
        sys.path.insert(0, os.getcwd())
    try:
        target: object = (
            _import_file(Path(module_name))
            if module_name.endswith(".py")
            else importlib.import_module(module_name)
        )
    except ConfigError:
        raise
    except (Exception, SystemExit) as exc:  # a user's module may do anything while it loads
        if isinstance(exc, SystemExit):
            raise ConfigError(
                f"handler {spec!r}: {module_name!r} called sys.exit({exc.code!r}) while it "
                "was imported"
            ) from None
        raise ConfigError(
            f"handler {spec!r}: cannot import {module_name!r}: {type(exc).__name__}: {exc}"
            + _module_hint(module_name, attr_path, exc)
        ) from exc
    try:
        return _resolve(spec, module_name, attr_path, target, bind=bind)
    except ConfigError:
        raise
    except (Exception, SystemExit) as exc:
        # A user's object runs code of its own when it is looked at (a ``__getattr__``, a
        # ``__class__`` or ``__signature__`` property) and may raise anything there: a
        # traceback in place of the one ``error:`` line.
        raise ConfigError(
            f"handler {spec!r}: looking up {attr_path!r} in {module_name!r} raised "
            f"{type(exc).__name__}: {exc}"
        ) from None


def _resolve(spec: str, module_name: str, attr_path: str, target: object, *, bind: bool) -> Handler:
    """``load_handler`` once the module is imported: the callable ``attr_path`` names in
    ``target``, checked (ConfigError naming what is wrong)."""
    found: list[str] = []
    for part in attr_path.split("."):
        owner = target
        try:
            target = getattr(target, part)
        except AttributeError as exc:
            # The whole name to write, not only its misspelt part (``Det.metod``: did you
            # mean 'Det.method'?).
            names = [".".join([*found, n]) for n in dir(target) if not n.startswith("_")]
            raise ConfigError(
                f"handler {spec!r}: {module_name!r} has no {attr_path!r}"
                + did_you_mean(".".join([*found, part]), names, quote=True)
            ) from exc
        found.append(part)
    if inspect.isclass(target):
        # ``module:Class``: built once, as for ``Class.method``, and its instances called.
        if not any("__call__" in vars(k) for k in target.__mro__):
            raise ConfigError(
                f"handler {spec!r} is a class whose instances cannot be called as "
                "handler(image, frame): it has no __call__ method"
            )
        what = f"{target.__name__} is a class"
        _check_signature(spec, target.__call__, self_too=True)
        _check_constructor(spec, target, what)
        return typing.cast(Handler, _instance(spec, target, what) if bind else target)
    method = inspect.isclass(owner) and inspect.isfunction(inspect.getattr_static(owner, part))
    if method and inspect.isclass(owner):  # ``module:Class.method``: an instance method
        what = f"{part!r} is an instance method"
        _check_signature(spec, target, self_too=True)
        _check_constructor(spec, owner, what)
        return typing.cast(Handler, getattr(_instance(spec, owner, what), part) if bind else target)
    if not callable(target):
        kind = type(target).__name__
        raise ConfigError(
            f"handler {spec!r} is {'an' if kind[:1] in 'aeiou' else 'a'} {kind}, not a "
            "function; it must be callable as handler(image, frame)"
        )
    _check_signature(spec, target, self_too=False)
    return typing.cast(Handler, target)


def _check_signature(spec: str, target: object, *, self_too: bool) -> None:
    """ConfigError unless ``target`` takes (image, frame) positionally (plus ``self`` for a
    method not yet bound), and returns its result rather than a coroutine or a generator:
    a wrong arity or an ``async def`` failed on every frame, counted, not at start."""
    function = inspect.unwrap(target)  # type: ignore[arg-type]
    if inspect.iscoroutinefunction(function) or inspect.isasyncgenfunction(function):
        raise ConfigError(
            f"handler {spec!r} is an async function: it is called once per frame and its "
            "result is needed, not a coroutine; define it with 'def' (asyncio.run() inside "
            "it runs async code)"
        )
    if inspect.isgeneratorfunction(function):
        raise ConfigError(
            f"handler {spec!r} is a generator function (it yields): return the list of "
            "boxes, or an Output, instead"
        )
    try:
        signature = inspect.signature(target)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return  # no signature to read (some built-ins): it is called as it is
    try:
        signature.bind(*([None] * (3 if self_too else 2)))
    except TypeError as exc:
        raise ConfigError(
            f"handler {spec!r} cannot be called as handler(image, frame): {exc}"
        ) from None


def _check_constructor(spec: str, cls: type, what: str) -> None:
    """ConfigError unless ``cls()`` can be called with no arguments, read from its signature
    without creating it: so ``launch --check`` and the flag check refuse what the runner
    could never build (it restarted forever), without loading a model."""
    try:
        signature = inspect.signature(cls)
    except (TypeError, ValueError):
        return  # no signature to read: creating it says
    try:
        signature.bind()
    except TypeError as exc:
        raise ConfigError(
            f"handler {spec!r}: {what}, and {cls.__name__}() failed: TypeError: {exc} "
            f"(it is created once, with no arguments)"
        ) from None


def _instance(spec: str, cls: type, what: str) -> object:
    """``cls()``: a handler's class is created once, with no arguments (a handler that keeps
    a model loads it in ``__init__``)."""
    try:
        return cls()
    except (Exception, SystemExit) as exc:
        raise ConfigError(
            f"handler {spec!r}: {what}, and {cls.__name__}() failed: {type(exc).__name__}: {exc}"
        ) from None


# Handler files loaded by path, so that one named twice (flag check, then run) loads once.
_FILES: dict[Path, ModuleType] = {}
# The module name a handler file is loaded under starts with this (``_import_file``).
_FILE_MODULE_PREFIX = "_framegate_handler_"


def handler_name(handler: Handler) -> str:
    """How a log line names ``handler``: ``module:function``, or ``path/file.py:function``
    for a handler loaded from a file (not the private module name it is loaded under)."""
    try:
        module = getattr(handler, "__module__", None) or type(handler).__module__
        name = getattr(handler, "__qualname__", type(handler).__qualname__)
    except Exception:  # a handler object's own __getattr__ may raise anything
        module, name = type(handler).__module__, type(handler).__qualname__
    if module.startswith(_FILE_MODULE_PREFIX):
        module = getattr(sys.modules.get(module), "__file__", None) or module
    return f"{module}:{name}"


def _import_file(path: Path) -> ModuleType:
    """The module in ``path``, loaded under a name of its own (so a file called
    ``json.py`` is that file, not the standard library's)."""
    path = path.resolve()
    if path in _FILES:
        return _FILES[path]
    if not path.is_file():
        raise ConfigError(f"handler file {str(path)!r} does not exist" + _file_hint(path))
    if str(path.parent) not in sys.path:
        sys.path.insert(0, str(path.parent))
    name = f"{_FILE_MODULE_PREFIX}{len(_FILES)}_{path.stem}"
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None  # a .py path always has a loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses and pickling look their module up here
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    _FILES[path] = module
    return module


def _module_hint(module_name: str, attr_path: str, exc: BaseException) -> str:
    """A did-you-mean for a misspelt module of the handler's own name (not for a module
    that the handler's module imports and that is missing: that is the user's to install),
    or for a path written where a module name goes."""
    if module_name.endswith(".py"):  # a file, found and named right: its own error says why
        return _package_hint(Path(module_name), attr_path, exc)
    if "/" in module_name:  # a path without its .py: say how to name the file
        named = module_name.rstrip("/")
        if Path(named + ".py").is_file():
            return f" (did you mean '{named}.py:{attr_path}'?)"
        return f" (a handler file is named with its .py: 'path/to/file.py:{attr_path}')"
    missing = getattr(exc, "name", None)
    if not isinstance(exc, ModuleNotFoundError) or not isinstance(missing, str):
        return ""
    if module_name != missing and not module_name.startswith(missing + "."):
        return ""
    parent, _, leaf = missing.rpartition(".")
    if not parent:  # a top-level name: one of the user's, or not importable from here
        return _top_level_hint(leaf, module_name[len(missing) :], attr_path)
    try:
        where = importlib.import_module(parent).__path__
        siblings = [m.name for m in pkgutil.iter_modules(where)]
        # A directory without __init__.py imports too (a namespace package, as examples/),
        # but iter_modules lists none.
        siblings += [d.name for e in where if os.path.isdir(e) for d in os.scandir(e)
                     if d.is_dir() and d.name.isidentifier()]  # fmt: skip
    except Exception:  # the parent imported before; a search path that cannot be listed
        return ""
    hint = closest(leaf, siblings)
    if hint is None:
        return ""
    fixed = ".".join(filter(None, [parent, hint])) + module_name[len(missing) :]
    return f" (did you mean {fixed!r}?)"


def _package_hint(path: Path, attr_path: str, exc: BaseException) -> str:
    """For a file of a package that imports its siblings relatively (``from .util import
    g``): loaded by path it has no package, so name it as the package's module."""
    if not isinstance(exc, ImportError) or "relative import" not in str(exc):
        return ""
    root = path.resolve().parent
    while (root / "__init__.py").is_file():
        root = root.parent
    dotted = ".".join(path.resolve().relative_to(root).with_suffix("").parts)
    if "." not in dotted:  # not in a package: nothing to name it by
        return ""
    where = "" if root == Path.cwd() else f" and run from {str(root)!r} (or add it to PYTHONPATH)"
    return f" (it is a module of a package: name it '{dotted}:{attr_path}'{where})"


def _top_level_hint(leaf: str, rest: str, attr_path: str) -> str:
    """A misspelt top-level module is looked for among the user's own (the current directory
    and ``PYTHONPATH``), never among the standard library's and installed packages' hundreds
    of names, which make nonsense guesses (``examples`` read as ``tempfile``). Without a
    guess, say how a module of one's own becomes importable."""
    roots = [os.getcwd(), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    names: list[str] = []
    for root in roots:
        with contextlib.suppress(OSError):
            for entry in os.scandir(root):
                name = entry.name[:-3] if entry.name.endswith(".py") else entry.name
                if name.isidentifier() and (entry.is_dir() or entry.name.endswith(".py")):
                    names.append(name)
    hint = closest(leaf, names)
    if hint is not None:
        return f" (did you mean {hint + rest!r}?)"
    return (
        f" (a module of your own imports from the directory that holds it: run from there, "
        f"add it to PYTHONPATH, or name the file: 'path/to/file.py:{attr_path}')"
    )


def _file_hint(path: Path) -> str:
    """A did-you-mean for a handler file that does not exist: a sibling ``.py`` file of a
    like name, or the module path written with dots (``pkg.mod.py`` for ``pkg/mod.py``)."""
    dotted = path.parent / (path.stem.replace(".", "/") + ".py")
    if "." in path.stem and dotted.is_file():
        return f" (did you mean '{os.path.relpath(dotted)}'?)"
    try:
        siblings = [p.name for p in path.parent.glob("*.py")]
    except OSError:
        return ""
    hint = closest(path.name, siblings)
    return "" if hint is None else f" (did you mean '{os.path.relpath(path.parent / hint)}'?)"


def handler_argument(spec: str) -> str:
    """argparse type of ``--handler``: the spec, once it names a callable (so a deploy file
    naming a missing handler fails ``launch --check``); in a child process within
    ``checked_apart``."""
    try:
        if _APART.get():
            _check_in_child(spec)
        else:
            load_handler(spec, bind=False)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc
    return spec


# Set by ``checked_apart``: the flags are checked by a process that will not run the handler.
_APART: ContextVar[bool] = ContextVar("handler_checked_apart", default=False)
# A module may take long to import (a framework, a model), but a check must end.
_CHILD_CHECK_S = 300.0
# What the child prints before a ConfigError's message, so that a module's own output on
# stderr is not taken for it.
_MARK = "framegate-handler-check: "
_CHILD = f"""
import sys
from middleware import ConfigError
from services.nodes._vision_handler import load_handler
try:
    load_handler(sys.argv[1], bind=False)
except ConfigError as exc:
    sys.stderr.write({_MARK!r} + str(exc) + "\\n")
    sys.exit(2)
"""


@contextlib.contextmanager
def checked_apart() -> Iterator[None]:
    """Within it, ``--handler`` is checked in a short-lived child process (a launcher's)."""
    token = _APART.set(True)
    try:
        yield
    finally:
        _APART.reset(token)


def _check_in_child(spec: str) -> None:
    """``load_handler(spec, bind=False)`` in a child process (same interpreter, directory and
    environment, so the same modules are found); ConfigError with its message."""
    try:
        done = subprocess.run(
            [sys.executable, "-c", _CHILD, spec],
            capture_output=True,
            text=True,
            timeout=_CHILD_CHECK_S,
            check=False,
        )
    except subprocess.TimeoutExpired:
        raise ConfigError(
            f"handler {spec!r}: its module was still importing after {_CHILD_CHECK_S:g} s"
        ) from None
    if done.returncode == 0:
        return
    said = [line for line in done.stderr.splitlines() if line.startswith(_MARK)]
    if said:
        raise ConfigError(said[-1][len(_MARK) :])
    last = done.stderr.strip().splitlines()[-1:] or ["no output"]
    raise ConfigError(
        f"handler {spec!r}: checking it in a child process failed "
        f"(exit {done.returncode}): {last[0][:200]}"
    )


def result_kind(handler: Handler, requested: str) -> ResultKind:
    """The output's kind: ``requested`` unless ``auto``; then the handler's return annotation
    (``Output``, ``bytes`` or a ``dict``/``Mapping`` of fields → generic), and detections for
    anything else or none."""
    if requested != "auto":
        return ResultKind(requested)
    # A callable object (a class with state, such as the previous frame) declares it on
    # its __call__.
    function = handler if inspect.isroutine(handler) else type(handler).__call__
    try:
        returns = typing.get_type_hints(function).get("return")
    except Exception:  # unresolvable (``Output`` imported under TYPE_CHECKING): read the text
        raw = getattr(function, "__annotations__", {}).get("return")
        names = set(re.findall(r"\w+", raw)) if isinstance(raw, str) else set()
        generic_names = {"Output", "bytes", "dict", "Mapping"}
        return ResultKind.GENERIC if names & generic_names else ResultKind.DETECTIONS
    # Compared by identity: an annotation may be any object (``-> [Box]`` is a list, which
    # a set cannot hold; another's ``__eq__`` may raise), and the runner failed to start.
    # The members of a union (``Output | None``), not the items of a container: ``list[dict]``
    # is a list, of boxes gone wrong; ``dict[str, float]`` is compared by its origin, ``dict``.
    union = typing.get_origin(returns) in (typing.Union, types.UnionType)
    options = [*typing.get_args(returns)] if union else [returns]
    origins = [typing.get_origin(option) or option for option in options]
    return ResultKind.GENERIC if any(map(_generic, origins)) else ResultKind.DETECTIONS


def _generic(annotation: object) -> bool:
    """Whether a return annotation names a generic result: Output, bytes, or a mapping of
    fields (``dict``, ``Mapping``, a ``TypedDict``, which is a dict); any other object, or
    a class whose subclass check raises, is not."""
    if not isinstance(annotation, type):
        return False
    try:
        return issubclass(annotation, Output | bytes | Mapping)
    except Exception:
        return False
