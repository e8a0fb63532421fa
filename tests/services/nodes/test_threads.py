"""The Python threads of a running camera, mediator and detector against docs/threads.md:
every thread a process runs has its row there (for that process), at most once, and the
node's own threads are there (one executor per node)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from middleware import FramegateError, ServiceInfo
from services.launch import pipeline_yaml
from tests.conftest import REPO, wait_until
from tests.services.nodes.pipeline import Pipeline

pytestmark = pytest.mark.integration

SERVICES = ("camera", "mediator", "detector")


def table() -> dict[str, set[str]]:
    """Thread name (``<service>`` and ``<node>`` as placeholders) -> the processes the
    table says run it (``all``: every process; ``all services``: every service)."""
    rows: dict[str, set[str]] = {}
    text = (REPO / "docs" / "threads.md").read_text()
    section = text.split("## Python threads", 1)[1].split("\n## ", 1)[0]
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 2 or not cells[0].startswith("`"):
            continue
        for name in re.findall(r"`([^`]+)`", cells[0]):
            # "all services (a note)": the note is for the reader.
            rows[name] = {p.split("(")[0].strip() for p in cells[1].split(",")}
    return rows


def allowed(service: str, rows: dict[str, set[str]]) -> set[str]:
    names = set()
    for name, processes in rows.items():
        if processes & {"all", "all services"} or service in processes:
            names.add(name.replace("<service>", service).replace("<node>", service))
    return names


def test_the_table_parses() -> None:
    rows = table()
    assert {"MainThread", "fg-exec-<node>", "fg-serve-<service>"} <= set(rows)
    assert "camera" in allowed("camera", rows) or "fg-exec-camera" in allowed("camera", rows)


def test_running_services_run_the_threads_of_the_table(tmp_path: Path) -> None:
    rows = table()
    pipe = Pipeline(tmp_path, pipeline_yaml({"camera": {"seed": 3}, "gyro": {"seed": 3}}))
    try:
        # Once the detector has stored something, every stage is past its start-up.
        wait_until(lambda: pipe.counter("detector/detections") > 0, 90, "detections")
        infos: dict[str, ServiceInfo] = {}

        def described() -> bool:
            for service in SERVICES:
                try:
                    infos[service] = pipe.node.service_info(service, timeout_s=2.0)
                except FramegateError:
                    return False
            return True

        wait_until(described, 30, "every service's description")
        for service in SERVICES:
            threads = infos[service].threads
            assert threads is not None, f"{service} does not list its threads"
            names = list(threads)
            expected = allowed(service, rows)
            unlisted = sorted(n for n in names if n not in expected)
            assert not unlisted, (
                f"{service} runs threads docs/threads.md does not list for it: {unlisted} "
                f"(all: {names})"
            )
            doubled = sorted({n for n in names if names.count(n) > 1})
            assert not doubled, f"{service} runs these more than once: {doubled}"
            for own in ("MainThread", f"fg-exec-{service}", f"fg-serve-{service}"):
                assert own in names, f"{service} lacks {own}: {names}"
    finally:
        pipe.close()
