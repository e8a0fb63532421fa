"""The README, the reference pages in docs/ and the deploy files agree with the repository:
every file they name exists, every link between them leads somewhere, and every
``framegate ...`` command line they show parses (parsed only, never run)."""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from services.cli import COMMANDS, build_parser
from services.cli.run import service_parser
from services.nodes import SERVICES
from tests.conftest import REPO

README = REPO / "README.md"
PAGES = sorted((REPO / "docs").glob("*.md"))
# The README and every reference page: each command and claim is checked wherever it lives.
MARKDOWN = [README, *PAGES]
DEPLOY_FILES = sorted(p for p in (REPO / "deploy").glob("*") if p.is_file())
# Directories of the repository itself: a path starting with one of them must exist.
ROOTS = ("deploy", "services", "tests", "middleware", "schemas", "examples", "docs", ".ci")
_PATH = re.compile(rf"(?<![\w./-])((?:{'|'.join(re.escape(r) for r in ROOTS)})/[\w./*-]*\w)")
# Written by a command the docs show, not shipped (deploy/tls/make-certs.sh makes the certs).
GENERATED = ("deploy/tls/certs",)
_SHELL_ENDS = {"|", "||", "&&", ";", "&", ">", ">>", "2>", "2>&1"}


def _documents() -> list[Path]:
    return [*MARKDOWN, *DEPLOY_FILES]


def _where(doc: Path, number: int) -> str:
    return f"{doc.relative_to(REPO)}:{number}"


def _mentioned_paths() -> list[tuple[str, str]]:
    found = []
    for doc in _documents():
        for match in _PATH.finditer(doc.read_text()):
            path = match.group(1).rstrip(".")
            if not path.startswith(GENERATED) and "<" not in path:
                found.append((str(doc.relative_to(REPO)), path))
    return found


# A placeholder in a command's synopsis (FILE, SERVICE/BUFFER, [--json], A | B).
_PLACEHOLDER = re.compile(r"\[|\||(?<![\w-])[A-Z][A-Z/_.]*(?![\w-])")


def _inline_commands() -> list[tuple[str, str]]:
    """(where, text) of each whole ``framegate ...`` command quoted in the docs' prose and
    tables; synopses with placeholders are left out (their flags are in --help)."""
    found = []
    for doc in MARKDOWN:
        for number, line in enumerate(doc.read_text().splitlines(), 1):
            if line.startswith("```"):
                continue
            for match in re.finditer(r"`(framegate [^`]+)`", line):
                words = match.group(1).split()[1:]
                # `framegate record` (or `framegate run vision`) alone names the command in
                # a sentence; with arguments it is a command line the reader may copy.
                naming = len(words) == 1 or (len(words) == 2 and words[0] == "run")
                if not naming and not _PLACEHOLDER.search(" ".join(words)):
                    found.append((_where(doc, number), match.group(1)))
    return found


def _command_lines() -> list[tuple[str, list[str]]]:
    """(where, words after ``framegate``) of each command in the docs' code blocks and in the
    deploy files' comments."""
    lines: list[tuple[str, str]] = []
    for doc in MARKDOWN:
        in_block = False
        for number, line in enumerate(doc.read_text().splitlines(), 1):
            if line.startswith("```"):
                in_block = not in_block
                continue
            if in_block:
                lines.append((_where(doc, number), line))
    for doc in DEPLOY_FILES:
        for number, line in enumerate(doc.read_text().splitlines(), 1):
            comment = line.lstrip()
            if comment.startswith(("#", "//")):
                text = comment.lstrip("#/ ")
                # A command (`framegate ...`, `robot$ framegate ...`), not prose naming it.
                if re.match(r"([\w-]*\$\s*)?framegate\s", text):
                    lines.append((f"{doc.name}:{number}", text))
    lines += _inline_commands()
    commands = []
    for where, line in lines:
        code = re.sub(r"^\s*[\w-]*\$\s*", "", line)  # a `robot$ ` prompt
        try:
            words = shlex.split(code, comments=True)
        except ValueError:
            continue
        while "framegate" in words:
            words = words[words.index("framegate") + 1 :]
            command = []
            for word in words:
                if word in _SHELL_ENDS:
                    break
                command.append(word)
            if "..." in command:
                continue  # elided on purpose: not a whole command line
            if (command and not command[0].startswith("-")) or command == ["--help"]:
                commands.append((where, command))
    return commands


def test_the_docs_name_paths_and_commands_to_check() -> None:
    # A broken extractor would make the tests below pass vacuously.
    assert len(_mentioned_paths()) > 20
    assert len(_command_lines()) > 20


@pytest.mark.parametrize(("doc", "path"), _mentioned_paths())
def test_every_path_the_docs_name_exists(doc: str, path: str) -> None:
    exists = any(REPO.glob(path)) if "*" in path else (REPO / path).exists()
    assert exists, f"{doc} names {path}, which does not exist"


# Command lines the README shows that do not parse yet, in sections this test's owners do
# not edit; strict, so that the fix makes this list shrink.
KNOWN_BROKEN: set[str] = set()  # command lines the README is known to show wrongly


def _command_params() -> list[object]:
    return [
        pytest.param(
            where,
            words,
            id=f"{where}:{shlex.join(words)}",
            marks=[pytest.mark.xfail(strict=True, reason="the README shows it wrongly")]
            if shlex.join(words) in KNOWN_BROKEN
            else [],
        )
        for where, words in _command_lines()
    ]


@pytest.mark.parametrize(("where", "words"), _command_params())
def test_every_command_line_in_the_docs_parses(where: str, words: list[str]) -> None:
    if "--help" in words or "-h" in words:
        return  # asks for help: nothing else to parse
    parser = build_parser(words[0])
    try:
        args = parser.parse_args(words)
        if words[0] == "run":
            service_parser(args.service).parse_args(args.args)
    except SystemExit as exc:
        pytest.fail(f"{where}: framegate {shlex.join(words)} does not parse (exit {exc.code})")


# A Markdown link outside code: [text](target), the target relative to the page.
_LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to dashes."""
    text = re.sub(r"[`*]", "", heading.strip().lstrip("#").strip()).lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors(doc: Path) -> set[str]:
    anchors, in_block = set(), False
    for line in doc.read_text().splitlines():
        if line.startswith("```"):
            in_block = not in_block
        elif not in_block and line.startswith("#"):
            anchors.add(_slug(line))
    return anchors


def _links() -> list[tuple[str, Path, str]]:
    """(where, page, target) of every relative link in the README and docs/."""
    found = []
    for doc in MARKDOWN:
        in_block = False
        for number, line in enumerate(doc.read_text().splitlines(), 1):
            if line.startswith("```"):
                in_block = not in_block
                continue
            if in_block:
                continue
            for match in _LINK.finditer(line):
                target = match.group(1)
                if not re.match(r"[a-z]+:", target):  # http:, https:, mailto:
                    found.append((_where(doc, number), doc, target))
    return found


def test_the_docs_have_links_to_check() -> None:
    assert len(_links()) > 15


@pytest.mark.parametrize(
    ("where", "doc", "target"),
    [pytest.param(*link, id=f"{link[0]}:{link[2]}") for link in _links()],
)
def test_every_link_in_the_docs_leads_somewhere(where: str, doc: Path, target: str) -> None:
    path, _, anchor = target.partition("#")
    page = (doc.parent / path).resolve() if path else doc
    assert page.exists(), f"{where} links to {target}: no such file"
    if anchor and page.suffix == ".md":
        assert anchor in _anchors(page), f"{where} links to {target}: no such heading"


def _headless_tables() -> list[str]:
    """Where a block of table rows (outside code blocks) has no header and separator row:
    Markdown then shows the rows as plain text, pipes and all."""
    bad: list[str] = []
    for doc in MARKDOWN:
        block: list[tuple[int, str]] = []
        fenced = False
        for number, line in enumerate([*doc.read_text().splitlines(), ""], 1):
            fenced ^= line.startswith("```")
            if line.startswith("|") and not fenced:
                block.append((number, line))
                continue
            if block and not re.fullmatch(r"\|[\s:|-]+\|", block[1][1] if len(block) > 1 else ""):
                bad.append(_where(doc, block[0][0]))
            block = []
    return bad


def test_every_table_in_the_docs_has_its_header() -> None:
    assert not _headless_tables(), f"table rows without a header row: {_headless_tables()}"


def test_the_readme_links_every_reference_page() -> None:
    linked = {
        (README.parent / t.partition("#")[0]).resolve() for _, d, t in _links() if d == README
    }
    missing = [p.name for p in PAGES if p.resolve() not in linked]
    assert not missing, f"docs pages the README does not link to: {missing}"


def test_the_readme_is_a_guide_not_a_reference() -> None:
    # Reference material belongs in docs/; the README stays short enough to read to the end.
    lines = len(README.read_text().splitlines())
    assert lines <= 420, f"README.md has {lines} lines; move reference material to docs/"


def test_the_readme_tells_ros2_users_which_rmw_to_use() -> None:
    # Nodes on ROS 2's default RMW (DDS) never meet the bridge's Zenoh topics.
    section = README.read_text().split("## With ROS 2", 1)[1].split("\n## ", 1)[0]
    assert "RMW_IMPLEMENTATION=rmw_zenoh_cpp" in section


def _help_text(words: list[str]) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        if words[0] == "run" and len(words) > 2:
            service_parser(words[1]).parse_args(["--help"])
        else:
            build_parser(words[0]).parse_args(words)
    return out.getvalue()


@pytest.mark.parametrize(
    "words",
    [[name, "--help"] for name in COMMANDS] + [["run", name, "--help"] for name in SERVICES],
    ids=lambda words: " ".join(words[:-1]),
)
def test_help_texts_show_no_markup(words: list[str]) -> None:
    # A terminal shows reST ``literals`` and Markdown `code` as the raw marks.
    text = _help_text(words)
    assert text.strip(), f"framegate {' '.join(words)} printed nothing"
    assert "`" not in text, f"framegate {' '.join(words)} shows markup:\n{text}"


def test_a_directory_that_is_no_dataset_is_told_where_the_layout_is(tmp_path: Path) -> None:
    # `calibrate DIR` on a `query --save` directory: the error must name a file the user can
    # open, wherever framegate is installed (DATASET.md ships as package data).
    from services.lib.sim import DatasetError, read_dataset

    (tmp_path / "000001.png").write_bytes(b"")
    with pytest.raises(DatasetError, match="framegate simulate") as caught:
        read_dataset(tmp_path)
    named = re.search(r"layout is in (\S+DATASET\.md)", str(caught.value))
    assert named is not None, str(caught.value)
    assert Path(named.group(1)).is_file()


def test_the_commands_said_to_work_without_connection_flags_are_those_that_have_none() -> None:
    """The README listed `simulate`, `calibrate`, `bench` and `experiment`; `soak` and
    `faults` have no `--connect` either (each runs its own pipeline on a private port)."""
    without = set()
    for name in COMMANDS:
        if name == "run":  # each service type has its own parser, with the flags
            continue
        sub = next(a for a in build_parser(name)._actions if a.dest == "command")
        command = sub.choices[name]  # type: ignore[index]
        if "--connect" not in {f for a in command._actions for f in a.option_strings}:
            without.add(name)
    for doc in (README, REPO / "docs" / "cli.md"):
        text = " ".join(doc.read_text().split())
        match = re.search(r"`--no-shm`; ((?:`\w+`,? )+)and `(\w+)` work offline", text)
        assert match, doc
        said = {*re.findall(r"`(\w+)`", match.group(1)), match.group(2)}
        assert said == without, (doc.name, sorted(said), sorted(without))
