"""The pipeline is defined once: deploy/local.yaml, demo, soak and the tests all agree."""

from __future__ import annotations

import pytest

from middleware import ConfigError
from services.evidence.soak import SoakConfig, soak_deployment
from services.launch import Deployment, load_deployment, parse_deployment, pipeline, pipeline_yaml
from services.tools.demo import DemoConfig, demo_deployment
from tests.conftest import REPO


def _services(deployment: Deployment) -> dict[str, tuple[str, tuple[str, ...]]]:
    return {s.name: (s.type, tuple(sorted(s.args))) for s in deployment.services}


def test_local_deploy_file_mirrors_the_pipeline_definition() -> None:
    # The one difference: a user's launch plays the approach prerendered (as the demo).
    prerendered = {"camera": {"source": "prerendered"}, "gyro": {"source": "prerendered"}}
    assert _services(load_deployment(REPO / "deploy" / "local.yaml")) == _services(
        pipeline(prerendered)
    )


def test_pipeline_yaml_says_what_pipeline_says() -> None:
    overrides = {"camera": {"seed": 7}, "mediator": None}
    parsed = parse_deployment(pipeline_yaml(overrides), "generated.yaml")
    assert _services(parsed) == _services(pipeline(overrides))


def test_overrides_change_drop_and_remove() -> None:
    deployment = pipeline({"detector": {"service_factor": None, "queue": 5}, "gyro": None})
    args = {s.name: s.args for s in deployment.services}
    assert list(args) == ["camera", "mediator", "detector"]
    assert "--service-factor" not in args["detector"]
    assert args["detector"][args["detector"].index("--queue") + 1] == "5"
    with pytest.raises(ConfigError, match="no pipeline service lidar"):
        pipeline({"lidar": {}})


def _without(argv: tuple[str, ...], flag: str) -> tuple[str, ...]:
    if flag not in argv:
        return argv
    i = argv.index(flag)
    return argv[:i] + argv[i + 2 :]


def test_demo_and_soak_default_to_the_shipped_pipeline() -> None:
    shipped = {s.name: s.args for s in pipeline().services}
    # The demo's live-rendering variant runs the shipped pipeline plus the uncontrolled
    # detector (same speed, on the camera's frames); by default it plays a prerendered
    # approach on the rough floor instead of rendering live.
    demo = {
        s.name: s.args for s in demo_deployment(DemoConfig(source="sim", floor="default")).services
    }
    uncontrolled = demo.pop("uncontrolled")
    assert demo == shipped
    assert _without(uncontrolled, "--input")[:2] == ("--name", "uncontrolled")
    assert uncontrolled[uncontrolled.index("--input") + 1] == "camera/images"
    assert "--observe" in uncontrolled
    assert _without(_without(uncontrolled, "--name"), "--input")[:-1] == _without(
        shipped["detector"], "--input"
    )
    camera = demo_deployment(DemoConfig()).services[0].args
    assert camera[camera.index("--source") + 1] == "prerendered"
    assert camera[camera.index("--floor") + 1] == "rough"
    soak = soak_deployment(SoakConfig(service_factor=1.6))
    # The soak adds only its replay rate.
    assert {s.name: _without(s.args, "--rate") for s in soak.services} == shipped
