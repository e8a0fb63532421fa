"""Mistakes on the command line give one actionable line and exit 1; start-up stays light."""

from __future__ import annotations

import argparse
import subprocess

import pytest

from services.cli import COMMANDS, build_parser
from tests.conftest import free_port, run_framegate, start_python
from tests.helpers.imports import modules_after
from tests.helpers.timing import scaled

# Modules that the listed commands must not pay for (seconds of start-up on a small machine).
HEAVY = ("cv2", "numpy", "matplotlib", "foxglove", "foxglove_websocket", "scipy", "mcap")

# Positional arguments (and required flags) a command needs to parse at all.
REQUIRED: dict[str, tuple[str, ...]] = {
    "launch": ("deploy/local.yaml",),
    "run": ("camera",),
    "info": ("camera/images",),
    "query": ("camera/images",),
    "echo": ("camera/images",),
    "watch": ("camera/images",),
    "hz": ("camera/images",),
    "pub": ("t/x", "--kind", "generic"),
    "record": ("camera/images", "-o", "x.mcap"),
    "play": ("x.mcap",),
    "calibrate": ("dataset",),
    "simulate": ("--out", "dataset"),
    "experiment": ("--out", "results"),
}


def _framegate(*args: str) -> subprocess.CompletedProcess[str]:
    return run_framegate(*args, timeout_s=120)


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (("lss",), "(did you mean ls?)"),
        (("sl",), "(did you mean ls?)"),  # two letters swapped
        (("query", "camera/images", "--lats", "3"), "unknown option '--lats' (did you mean --last?)"),  # noqa: E501
        (("query", "camera/images", "--from", "-5x"), "bad time '-5x' for --from"),
        (("run", "camera", "--source", "sim", "--rate", "nan"), "argument --rate: must be a number >= 1e-09 and <= 1e+09, got 'nan'"),  # noqa: E501
        # A rate whose period no thread can wait (OverflowError tracebacks before).
        (("run", "camera", "--source", "sim", "--rate", "1e-300"), "argument --rate: must be a number >= 1e-09 and <= 1e+09, got '1e-300'"),  # noqa: E501
        (("pub", "t/x", "--kind", "generic", "--rate", "1e-12"), "argument --rate: must be a number >= 1e-09 and <= 1e+09, got '1e-12'"),  # noqa: E501
        (("run", "camera", "--retention-frames", "0"), "argument --retention-frames: must be an integer > 0"),  # noqa: E501
        (("run", "gyro", "--rate", "inf"), "argument --rate: must be a number >= 1e-09 and <= 1e+09, got 'inf'"),  # noqa: E501
        (("run", "ros2", "--consumer-timeout-ms", "1e303"), "argument --consumer-timeout-ms: must be a number > 0 and <= 1e+09, got '1e303'"),  # noqa: E501
        (("run", "gyro", "--frames", "-5"), "argument --frames: must be an integer > 0, got '-5'"),
        (("run", "mediator", "--q-min", "2"), "argument --q-min: must be a number >= 0 and <= 1"),
        (("run", "camera", "--sorce", "sim"), "(did you mean --source?)"),
        # A short flag meant for a required option: argparse said only "required: --out".
        (("simulate", "-o", "x"), "unknown option '-o' (did you mean --out?)"),
        (("run", "camra"), "(did you mean camera?)"),
        (("watch", "camera/images", "--queue", "0"), "argument --queue: must be an integer > 0"),
        (("echo", "camera/images", "--count", "-1"), "argument --count: must be an integer > 0"),
        (("pub", "t/x", "--kind", "fram"), "(did you mean frame?)"),
        (("launch", "deploy/local.yaml", "--status", "0"), "argument --status: must be a number > 0"),  # noqa: E501
        (("record", "camera/images", "-o", "x.mcap", "--duration", "nan"), "argument --duration: must be a number > 0"),  # noqa: E501
        (("view", "--duration", "-1"), "argument --duration: must be a number > 0"),
        (("view", "--backlog", "0"), "argument --backlog: must be an integer > 0"),
        (("play", "x.mcap", "--rate", "nan"), "argument --rate: must be a number >= 0"),
        (("play", "x.mcap", "--start-delay", "inf"), "argument --start-delay: must be a number >= 0"),  # noqa: E501
        (("bench", "--pairs", "0"), "argument --pairs: must be an integer > 0"),
        (("demo", "--seed", "-1"), "argument --seed: must be an integer >= 0"),
        (("soak", "--seed", "-2"), "argument --seed: must be an integer >= 0"),
        (("simulate", "--seed", "-1", "--out", "x"), "argument --seed: must be an integer >= 0"),
        (("experiment", "--out", "x", "--seeds", "-1"), "argument --seeds: must be an integer >= 0"),  # noqa: E501
        # An observer's queue above the limit: named by its flag, not as queue_size, and
        # without the flow-control reason (echo only observes).
        (("echo", "t/x", "--queue", "100000000"), "argument --queue: must be an integer > 0 and <= 1048576, got '100000000'"),  # noqa: E501
        (("hz", "t/x", "--queue", "2000000"), "argument --queue: must be an integer > 0 and <= 1048576"),  # noqa: E501
        (("watch", "t/x", "--flow-control", "--queue", "40000"), "--queue 40000: at most 32768 with --flow-control"),  # noqa: E501
        ((), "name a command"),
    ],
)  # fmt: skip
def test_mistakes_are_one_line_with_exit_1(args: tuple[str, ...], expected: str) -> None:
    result = _framegate(*args)
    lines = [line for line in result.stderr.splitlines() if not line.startswith("usage:")]
    assert result.returncode == 1, result
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert expected in lines[0], result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (("topic", "echo", "camera/images"), "'ros2 topic echo' is 'framegate echo' here"),
        (("topic", "list"), "'ros2 topic list' is 'framegate ls' here"),
        (("topic", "bw", "camera/images"), "'ros2 topic bw' is 'framegate hz' here"),
        (("bag", "record", "-a"), "'ros2 bag record' is 'framegate record' here"),
        (("node", "list"), "'ros2 node list' is 'framegate ls' here"),
        (("topic",), "framegate has no 'topic' command: its ls, info, echo, hz and pub"),
        (("help",), "framegate has no 'help' command: framegate --help lists the commands"),
    ],
)  # fmt: skip
def test_a_ros2_command_gets_framegates_own_name(args: tuple[str, ...], expected: str) -> None:
    # A ROS 2 user's first try (`framegate topic echo ...`) listed twenty commands and left
    # them to guess which one answers `ros2 topic echo`.
    result = _framegate(*args)
    assert result.returncode == 1, result
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("error: "), result
    assert expected in result.stderr, result.stderr


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (("echo", "camera/images", "--once"), "unknown option '--once' (ros2's --once is --count 1 here)"),  # noqa: E501
        (("record", "-a", "-o", "x.mcap"), "unknown option '-a' (ros2's -a is --all here)"),
        (("play", "x.mcap", "-r", "2"), "unknown option '-r' (ros2's -r is --rate R here)"),
        (("play", "x.mcap", "--topics", "camera/images"), "(ros2's --topics is --only SERVICE/BUFFER here)"),  # noqa: E501
        (("hz", "camera/images", "-w", "10"), "(ros2's -w is --window N here)"),
        (("play", "x.mcap", "-l"), "expected one argument (-l is --listen here; ros2's -l is --loop)"),  # noqa: E501
        (("echo", "camera/images", "--lats"), "unknown option '--lats'; see framegate echo --help"),
    ],
)  # fmt: skip
def test_a_ros2_flag_gets_framegates_own_spelling(args: tuple[str, ...], expected: str) -> None:
    # `echo --once` was answered "(did you mean --json?)", `record -a` with no hint at all.
    result = _framegate(*args)
    assert result.returncode == 1, result
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("error: "), result
    assert expected in result.stderr, result.stderr


def _options_of(command: str) -> set[str]:
    parser = build_parser(only=command)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {s for a in sub.choices[command]._actions for s in a.option_strings}


def test_every_ros2_flag_names_a_flag_its_command_has() -> None:
    from services.lib.argtypes import ROS2_FLAGS, ROS2_SHADOWED

    for command, flags in ROS2_FLAGS.items():
        options = _options_of(command)
        for ros2, ours in flags.items():
            assert ros2 not in options, f"{command} {ros2} is a flag of its own"
            named = ours.split()[0]
            assert not named.startswith("--") or named in options, (command, ros2, ours)
    for command, flags in ROS2_SHADOWED.items():
        options = _options_of(command)
        for ros2, ours in flags.items():
            assert ros2 in options and ours in options, (command, ros2, ours)


def test_an_endpoint_without_a_port_is_named_with_exit_1() -> None:
    result = _framegate("ls", "--connect", "tcp/abc")
    assert result.returncode == 1, result
    assert result.stderr == "error: cannot reach tcp/abc (no port number: write " + (
        "tcp/HOST:PORT); is the router or service running there?\n"
    ), result.stderr
    for endpoint, port in (("tcp/127.0.0.1:1,bogus", "1,bogus"), ("tcp/127.0.0.1:abc", "abc")):
        result = _framegate("ls", "--connect", endpoint)
        assert result.returncode == 1, result
        assert result.stderr == (
            f"error: --connect {endpoint}: {port} is not a port number: use 1..65535\n"
        ), result.stderr


def test_ls_says_where_it_looked_when_nothing_answers() -> None:
    result = _framegate("ls", "--connect", "udp/127.0.0.1:1", "--timeout", "0.5")
    assert result.returncode == 1, result
    assert result.stderr.startswith("error: nothing answered via udp/127.0.0.1:1 (waited 0.5 s)"), (
        result.stderr
    )


def test_an_unreachable_connect_endpoint_is_named_with_exit_1() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # nobody listens there
    for args in (("ls",), ("info", "camera/images", "--timeout", "1")):
        result = _framegate(*args, "--connect", endpoint)
        assert result.returncode == 1, result
        assert result.stderr.startswith(f"error: cannot reach {endpoint} ("), result.stderr
        assert len(result.stderr.splitlines()) == 1, result.stderr


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (("--connect", "bogus"), "error: --connect: bad endpoint 'bogus': write PROTOCOL/"),
        (("--listen", "tcp/"), "error: --listen: bad endpoint 'tcp/': write PROTOCOL/"),
        (("--connect", "foo/bar"), "error: cannot open a Zenoh session (foo/bar): Unicast not"),
    ],
)
def test_a_bad_endpoint_is_one_line_naming_it_without_zenoh_source_paths(
    args: tuple[str, ...], expected: str
) -> None:
    result = _framegate("ls", *args)
    assert result.returncode == 1, result
    assert result.stderr.startswith(expected), result.stderr
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert ".rs:" not in result.stderr and ".cargo" not in result.stderr, result.stderr


@pytest.mark.parametrize(
    "code",
    [
        "main(['--help'])",
        "main(['ls', '--help'])",
        "main(['--version'])",
        "main(['info', '--help'])",
        "build_parser('ls').parse_args(['ls'])",
        # ls run to its end (nobody answers there): what it imports to look counts too.
        "main(['ls', '--connect', 'tcp/127.0.0.1:1', '--timeout', '0.5'])",
    ],
)
def test_help_and_ls_import_nothing_heavy(code: str) -> None:
    script = (
        "import io, json, sys\n"
        "from contextlib import redirect_stderr, redirect_stdout\n"
        "from services.cli import build_parser, main\n"
        "with redirect_stdout(io.StringIO()), redirect_stderr(io.StringIO()):\n"
        f"    {code}\n"
    )
    loaded = modules_after(script)
    heavy = sorted({m.split(".")[0] for m in loaded} & set(HEAVY))
    assert heavy == [], f"{code} imported {heavy}"


def test_help_lists_every_command_and_each_has_a_parser() -> None:
    result = _framegate("--help")
    assert result.returncode == 0
    for name in COMMANDS:
        assert f"\n    {name}" in result.stdout, name
    for name in COMMANDS:  # each summary's module exists and registers that very command
        args = build_parser(name).parse_args([name, *REQUIRED.get(name, ())])
        assert args.command == name and callable(args.func), name


# Number flags whose range a later check states in one line (a port, a JPEG quality).
RANGE_CHECKED_LATER = {("view", "--port"), ("view", "--jpeg")}


def _number_flags(parser: argparse.ArgumentParser) -> list[str]:
    return [
        action.option_strings[-1]
        for action in parser._actions
        if action.type in (int, float) and action.option_strings
    ]


@pytest.mark.parametrize("command", list(COMMANDS))
def test_every_number_flag_is_checked_as_it_is_parsed(command: str) -> None:
    # A plain int/float type lets nan, inf, 0 or -5 through to fail later, or to do nothing.
    sub = next(
        a for a in build_parser(command)._actions if isinstance(a, argparse._SubParsersAction)
    )
    unchecked = [
        flag for flag in _number_flags(sub.choices[command])
        if (command, flag) not in RANGE_CHECKED_LATER
    ]  # fmt: skip
    assert not unchecked, f"framegate {command}: {unchecked} take plain int/float"


@pytest.mark.parametrize("args", [("--version",), ("ls", "--version")])
def test_version_prints_the_installed_version_and_exits_0(args: tuple[str, ...]) -> None:
    result = _framegate(*args)
    assert result.returncode == 0 and result.stderr == "", result
    assert result.stdout.startswith("framegate ") and len(result.stdout.splitlines()) == 1


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (
            ("run", "ros2", "--ros-connect", "tcp/localhost:99999", "--image-in", "/cam"),
            "error: --ros-connect tcp/localhost:99999: 99999 is not a port number",
        ),
        (("faults", "--port", "70000"), "argument --port: must be an integer >= 1 and <= 65535"),
        (("soak", "--port", "0"), "argument --port: must be an integer >= 1 and <= 65535"),
    ],
)
def test_a_bad_port_is_one_line_before_anything_starts(args: tuple[str, ...], says: str) -> None:
    result = _framegate(*args)
    assert result.returncode != 0, result
    assert result.stdout == "", result.stdout  # no start banner
    assert len(result.stderr.splitlines()) == 1 and says in result.stderr, result.stderr


def test_a_router_on_port_0_says_which_port_it_took() -> None:
    proc = start_python(["-m", "services.cli", "router", "--listen", "tcp/127.0.0.1:0"])
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
    finally:
        proc.terminate()
        proc.wait(timeout=scaled(10))
    assert line.startswith("router listening on tcp/127.0.0.1:"), line
    port = int(line.strip().rsplit(":", 1)[1])
    assert 0 < port < 65536, line


# Defaults a help line cannot usefully print: an empty list of overrides.
NO_DEFAULT_SHOWN = {("simulate", "--set")}


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_flag_with_a_default_says_it_in_its_help(name: str) -> None:
    """`demo --help` gave no default for --policy, --floor, --b0, --queue, --seed...: the
    README said "rough by default" and the help nothing (soak, faults, experiment too)."""
    parser = build_parser(name)
    [commands] = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    silent = [
        action.option_strings[-1]
        for action in commands.choices[name]._actions
        if action.option_strings
        and action.default not in (None, False, argparse.SUPPRESS)
        and not isinstance(action, argparse._StoreTrueAction | argparse._HelpAction)
        and (name, action.option_strings[-1]) not in NO_DEFAULT_SHOWN
        and "default" not in (action.help or "")
    ]
    assert silent == [], f"framegate {name}: no default in the help of {silent}"
