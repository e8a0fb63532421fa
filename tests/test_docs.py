"""The README and the deploy files agree with the repository: every file they name exists,
and every ``framegate ...`` command line they show parses (parsed only, never run)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from services.cli import build_parser
from services.cli.run import service_parser
from tests.conftest import REPO

README = REPO / "README.md"
DEPLOY_FILES = sorted(p for p in (REPO / "deploy").glob("*") if p.is_file())
# Directories of the repository itself: a path starting with one of them must exist.
ROOTS = ("deploy", "services", "tests", "middleware", "schemas", "examples", "docs", ".ci")
_PATH = re.compile(rf"(?<![\w./-])((?:{'|'.join(re.escape(r) for r in ROOTS)})/[\w./*-]*\w)")
# Written by a command the docs show, not shipped (deploy/tls/make-certs.sh makes the certs).
GENERATED = ("deploy/tls/certs",)
_SHELL_ENDS = {"|", "||", "&&", ";", "&", ">", ">>", "2>", "2>&1"}


def _documents() -> list[Path]:
    return [README, *DEPLOY_FILES]


def _mentioned_paths() -> list[tuple[str, str]]:
    found = []
    for doc in _documents():
        for match in _PATH.finditer(doc.read_text()):
            path = match.group(1).rstrip(".")
            if not path.startswith(GENERATED) and "<" not in path:
                found.append((doc.name, path))
    return found


# A placeholder in a command's synopsis (FILE, SERVICE/BUFFER, [--json], A | B).
_PLACEHOLDER = re.compile(r"\[|\||(?<![\w-])[A-Z][A-Z/_.]*(?![\w-])")


def _inline_commands() -> list[tuple[str, str]]:
    """(where, text) of each whole ``framegate ...`` command quoted in the README's prose and
    tables; synopses with placeholders are left out (their flags are in --help)."""
    found = []
    for number, line in enumerate(README.read_text().splitlines(), 1):
        if line.startswith("```"):
            continue
        for match in re.finditer(r"`(framegate [^`]+)`", line):
            words = match.group(1).split()[1:]
            # `framegate record` alone names the command in a sentence; with arguments it is
            # a command line the reader may copy.
            if len(words) > 1 and not _PLACEHOLDER.search(" ".join(words)):
                found.append((f"README.md:{number}", match.group(1)))
    return found


def _command_lines() -> list[tuple[str, list[str]]]:
    """(where, words after ``framegate``) of each command in README code blocks and in the
    deploy files' comments."""
    lines: list[tuple[str, str]] = []
    in_block = False
    for number, line in enumerate(README.read_text().splitlines(), 1):
        if line.startswith("```"):
            in_block = not in_block
            continue
        if in_block:
            lines.append((f"README.md:{number}", line))
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
