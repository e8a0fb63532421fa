"""The bridge's flags: mappings, QoS defaults, distro, namespace."""

from __future__ import annotations

import argparse

import pytest

from middleware import ConfigError
from services.nodes.ros2._config import Mapping, Ros2Config, add_arguments, config_from_args
from services.nodes.ros2._rmw import Reliability


def _config(*argv: str) -> Ros2Config:
    parser = argparse.ArgumentParser(exit_on_error=False)
    add_arguments(parser)
    return config_from_args(parser.parse_args(list(argv)))


def test_defaults_match_ros2_profiles() -> None:
    config = _config("--image-in", "/camera/image_raw")
    assert config.ros_connect == ("tcp/localhost:7447",)
    assert config.in_qos.keyexpr() == "2::,5:,:,:,,"  # sensor data: best effort, depth 5
    assert config.out_qos.keyexpr() == "::,10:,:,:,,"  # reliable, depth 10
    assert config.out_reliability is Reliability.RELIABLE


def test_mappings_from_flags_and_deploy_lists() -> None:
    config = _config(
        "--ros-namespace",
        "robot1",
        "--image-out",
        "mediator/images=image_filtered",
        "camera/images",
        "--verdicts-out",
        "mediator/decisions=/verdicts",
    )
    assert config.image_out == (
        Mapping("mediator/images", "/robot1/image_filtered"),
        Mapping("camera/images", "/camera/images"),
    )
    assert config.verdicts_out == (Mapping("mediator/decisions", "/verdicts"),)


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["--image-out", "images=/x"], "SERVICE/BUFFER"),
        (["--image-out", "mediator/images="], "bad mapping"),
        (["--image-in", "/a b"], "bad ROS 2 topic name"),
        # A bare buffer is carried to /SERVICE/BUFFER, which may be no ROS 2 name.
        (["--image-out", "my-cam/images"], r"name the topic: my-cam/images=/ros/topic"),
        # What --camera-xml overrides, given beside it: it was silently ignored.
        (
            ["--image-in", "/cam/image_raw", "--camera-xml", "c.xml", "--camera-info", "/ci"],
            "--camera-info /ci with --camera-xml",
        ),
        # An output on a topic the bridge reads: its own images came back in as frames.
        (
            ["--image-in", "/cam/image_raw", "--image-out", "mediator/images=/cam/image_raw"],
            r"reads /cam/image_raw \(--image-in\) and would read its own messages back",
        ),
        (
            ["--image-in", "/cam/image_raw", "--image-out", "mediator/images=/cam/camera_info"],
            r"reads /cam/camera_info \(the CameraInfo",
        ),
        (["--imu-in", "/imu", "--verdicts-out", "m/decisions=/imu"], r"reads /imu \(--imu-in\)"),
        (["--image-out", "m/images=/tf_static"], "the static transforms"),
        (
            ["--image-out", "m/images=/out", "--image-out", "camera/images=/out"],
            "outputs m/images=/out and camera/images=/out publish on one topic",
        ),
    ],
)
def test_bad_flags_are_one_line_errors(argv: list[str], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        _config(*argv)


@pytest.mark.parametrize(
    "argv",
    [
        ["--exposure-ms", "0"],
        ["--exposure-ms", "nan"],
        ["--gyro-batch", "0"],
        ["--retention-frames", "0"],
        ["--out-queue", "0"],
        ["--in-depth", "0"],
        ["--out-depth", "-1"],
        ["--gyro-wait-ms", "inf"],
        ["--domain-id", "-1"],
        # Finite, but no time in int nanoseconds: the bridge died of an OverflowError.
        ["--consumer-timeout-ms", "1e303"],
        ["--max-ahead-ms", "1e303"],
    ],
)
def test_bad_numbers_are_refused_as_parsed(argv: list[str]) -> None:
    """Checked by the flag's type, so a deploy file's `launch --check` refuses them too."""
    with pytest.raises(argparse.ArgumentError, match=argv[0]):
        _config(*argv)


def test_a_consumer_timeout_under_a_nanosecond_is_refused() -> None:
    # It became 0 ns: the bridge died of a ValueError traceback as the loop started.
    with pytest.raises(ConfigError, match="--consumer-timeout-ms must be at least 1e-06"):
        _config(
            *("--image-out", "mediator/images=/x", "--consumer-done", "/yolo"),
            *("--consumer-timeout-ms", "1e-7"),
        )


def test_a_bridge_with_nothing_to_carry_says_so() -> None:
    with pytest.raises(ConfigError, match="nothing to carry"):
        _config().check_has_work()


def test_ros_network_uses_the_ros_flags() -> None:
    network = _config("--ros-connect", "tcp/10.0.0.2:7447", "--image-in", "/c").ros_network()
    assert network.connect == ("tcp/10.0.0.2:7447",)


def test_a_ros_config_file_keeps_its_own_endpoints() -> None:
    config = _config("--ros-config", "ros.json5", "--image-in", "/c")
    assert config.ros_connect == ()
    assert _config("--ros-config", "r.json5", "--ros-connect", "tcp/h:7447").ros_connect == (
        "tcp/h:7447",
    )


def test_run_help_describes_the_bridge_in_one_whole_line() -> None:
    from services.nodes import describe

    # ``framegate run ros2 --help`` shows the first line of the package docstring.
    line = describe("ros2")
    assert line.endswith(".") and "rmw_zenoh" in line, line


def test_run_help_shows_every_default_a_flag_has() -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    text = parser.format_help()
    for default in ("default jazzy", "default framegate_bridge", "default 10.0", "default 5"):
        assert default in " ".join(text.split()), default


def test_a_deploy_list_of_routers_is_taken_whole() -> None:
    # `ros_connect: [tcp/a:7447, tcp/b:7447]` in a deploy file is one flag with two values.
    config = _config("--ros-connect", "tcp/a:7447", "tcp/b:7447", "--ros-connect", "tcp/c:7447")
    assert config.ros_connect == ("tcp/a:7447", "tcp/b:7447", "tcp/c:7447")


@pytest.mark.parametrize(
    "argv",
    [
        ["--consumer-queue", "3"],
        ["--consumer-queue", "2"],  # the default's value: given all the same
        ["--consumer-timeout-ms", "1000"],
        ["--consumer-input", "mediator/images"],
    ],
)
def test_a_loop_flag_without_consumer_done_is_refused_whatever_its_value(argv: list[str]) -> None:
    with pytest.raises(ConfigError, match=f"{argv[0]} without --consumer-done"):
        _config("--image-out", "mediator/images=/x", *argv)


def test_the_loop_flags_left_out_take_their_defaults() -> None:
    config = _config("--image-out", "mediator/images=/x", "--consumer-done", "/yolo")
    assert (config.consumer_queue, config.consumer_timeout_ms) == (2, 1000.0)
