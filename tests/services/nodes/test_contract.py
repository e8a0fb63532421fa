"""Every service keeps the one contract, and every config field can be set by a flag.

The flag check is behavioural: each of a service's flags is given a non-default value, and
the config fields that change are collected. A field no flag changes (today's
``lossless_wait_s``, ``retention_s``, ``max_hold_ms``) fails the test by name.
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

import pytest

from middleware import FramegateError, add_network_arguments
from services.nodes import SERVICES, service

# Fields a service's config carries but that do not apply to it, with the reason.
NOT_APPLICABLE = {
    # SourceSpec is shared with the camera; a gyro has no exposure or camera model.
    "gyro": {"source.exposure_ms", "source.camera_xml"},
}
# Flags that only make sense with another one (a replay needs its directory).
_LOOP = ["--consumer-done", "/yolo/detections", "--image-out", "mediator/images=/camera/sharp"]
COMPANIONS = {"--source": ["--path", "somewhere"]}
# Flags whose value is itself a list of words, or that need a companion to be valid.
WHOLE = {
    "--imu-to-camera": [["--imu-to-camera", "0", "0", "1", "-1", "0", "0", "0", "-1", "0"]],
    "--consumer-done": [_LOOP],
    # The loop's other flags are refused without it.
    "--consumer-input": [["--consumer-input", "mediator/images", *_LOOP]],
    "--consumer-queue": [["--consumer-queue", "3", *_LOOP]],
    "--consumer-timeout-ms": [["--consumer-timeout-ms", "500", *_LOOP]],
}
# Flags whose value must name something that exists (a handler is imported when parsed).
EXISTING = {"--handler": "services.nodes.detector:detect_aruco"}
# What a service cannot start without (argparse requires it), given to every parse.
REQUIRED = {"vision": ["--handler", "tests.services.nodes.vision_handlers:brightest"]}


def _parser(name: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(exit_on_error=False)
    service(name).add_arguments(parser)
    return parser


def _leaves(value: Any, prefix: str = "") -> dict[str, Any]:
    """Config fields by dotted path, nested dataclasses (the source) flattened."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(value):
        inner = getattr(value, f.name)
        if dataclasses.is_dataclass(inner) and not isinstance(inner, type):
            out.update(_leaves(inner, f"{prefix}{f.name}."))
        else:
            out[f"{prefix}{f.name}"] = inner
    return out


def _candidates(action: argparse.Action) -> list[list[str]]:
    """argv fragments giving ``action`` a value other than its default."""
    flag = action.option_strings[-1]
    if flag in EXISTING:
        return [[flag, EXISTING[flag]]]
    if flag in WHOLE:
        return WHOLE[flag]
    if action.nargs == 0:
        return [[flag]]
    if action.choices:
        extra = COMPANIONS.get(flag, [])
        return [[flag, str(c), *extra] for c in action.choices if str(c) != str(action.default)]
    if action.type is int or isinstance(action.default, int):
        return [[flag, str((action.default or 0) + 3)], [flag, "3"]]
    if action.type is float or isinstance(action.default, float):
        # A checked number type (positive_float, unit_float...): a value in every range.
        return [[flag, str((action.default or 0.0) + 0.5)], [flag, "0.5"], [flag, "3"]]
    return [[flag, "other"], [flag, "other/thing"], [flag, "3"], [flag, "0.5"]]


def _config(name: str, argv: list[str]) -> Any:
    parsed = _parser(name).parse_args([*REQUIRED.get(name, []), *argv])  # argv's value wins
    return service(name).config_from_args(parsed)


def _settable_fields(name: str) -> set[str]:
    default = _leaves(_config(name, []))
    changed: set[str] = set()
    for action in _parser(name)._actions:
        if not action.option_strings or action.dest == "help":
            continue
        for argv in _candidates(action):
            try:
                leaves = _leaves(_config(name, argv))
            except (FramegateError, argparse.ArgumentError, ValueError):
                continue
            changed |= {k for k, v in leaves.items() if v != default[k]}
    return changed


@pytest.mark.parametrize("name", SERVICES)
def test_service_keeps_the_contract(name: str) -> None:
    svc = service(name)
    assert svc.name == name
    assert dataclasses.is_dataclass(svc.config_type)
    assert svc.config_type.__dataclass_params__.frozen  # type: ignore[attr-defined]
    config = _config(name, [])
    assert isinstance(config, svc.config_type)
    assert callable(svc.run)


@pytest.mark.parametrize("name", SERVICES)
def test_run_help_describes_each_service_in_whole_sentences(name: str) -> None:
    from services.nodes import describe

    line = describe(name)  # what ``framegate run NAME --help`` shows first
    assert line.endswith(".") and "\n" not in line, line


@pytest.mark.parametrize("name", SERVICES)
def test_every_config_field_has_a_flag(name: str) -> None:
    fields = set(_leaves(_config(name, []))) - NOT_APPLICABLE.get(name, set())
    missing = fields - _settable_fields(name)
    assert not missing, f"{name}: config fields no flag sets: {sorted(missing)}"


def test_service_flags_do_not_clash_with_network_flags() -> None:
    for name in SERVICES:
        parser = argparse.ArgumentParser()
        add_network_arguments(parser)
        service(name).add_arguments(parser)  # argparse raises on a duplicate option


def test_registry_imports_nothing_heavy_until_asked() -> None:
    import subprocess
    import sys

    code = (
        "import sys, services.nodes, services.launch, services.cli.run;"
        "print(sorted(m for m in ('cv2', 'scipy', 'matplotlib') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
