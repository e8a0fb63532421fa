"""``record`` starts without the heavy imports and ends on time: a writer that falls behind
stores chunks uncompressed (a valid MCAP file of mixed chunks), and what the stop leaves
queued is written, not dropped."""

from __future__ import annotations

import random
import threading
from pathlib import Path

from middleware import DataObject, Retention, make_metadata
from services.tools.bag import BagWriter, Progress, WriteQueue, open_bag, recording_info
from tests.conftest import wait_until
from tests.helpers.imports import modules_after
from tests.helpers.timing import scaled

HEAVY = ("numpy", "foxglove", "cv2", "services.lib.quality", "services.lib.messages")
# Kinds whose channels need no Foxglove schema (decisions and detections are drawn with
# foxglove.ImageAnnotations, whose schema the file must hold before their first message).
PLAIN_KINDS = ("frame", "gyro", "camera", "generic")


def _element(t: int) -> DataObject:
    # Several 4 MiB chunks in all.
    return DataObject(t, random.Random(t).randbytes(200_000), make_metadata("generic", t))


def test_a_writer_that_is_behind_writes_uncompressed_chunks_and_loses_nothing(
    tmp_path: Path,
) -> None:
    path = tmp_path / "mixed.mcap"
    with BagWriter(path, images=False, compression="zstd") as writer:
        writer.add_buffer("cam", "log", kind="generic", retention=Retention())
        for t in range(1, 61):
            writer.catch_up(20 < t <= 40)  # behind for the middle third
            writer.write("cam/log", _element(t))
    info = recording_info(path)
    assert info.status == "complete" and info.messages == 60
    assert set(info.compressions) == {"zstd", "none"}, info.compressions
    with open_bag(path) as bag:
        got = [e for _, e in bag.elements()]
    assert [e.timestamp_ns for e in got] == list(range(1, 61))
    assert all(e.payload == _element(e.timestamp_ns).payload for e in got[::7])


def test_closing_the_write_queue_writes_what_is_queued_and_counts_later_puts_dropped(
    tmp_path: Path,
) -> None:
    path = tmp_path / "queue.mcap"
    progress = Progress("cam/log", "generic")
    with BagWriter(path, images=False, compression="zstd") as writer:
        writer.add_buffer("cam", "log", kind="generic", retention=Retention())
        queue = WriteQueue(writer)
        for t in range(1, 31):
            assert queue.put(progress, _element(t))
        queue.close()
        assert not queue.put(progress, _element(31))
    assert (progress.recorded, progress.dropped) == (30, 1)
    assert recording_info(path).messages == 30


class _HeldWriter:
    """A BagWriter stand-in whose first write waits until released (a slow disk)."""

    def __init__(self) -> None:
        self.writing, self.release = threading.Event(), threading.Event()
        self.written: list[int] = []

    def catch_up(self, _behind: bool) -> None:
        pass

    def write(self, _name: str, element: DataObject) -> None:
        self.writing.set()
        self.release.wait(scaled(30))
        self.written.append(element.timestamp_ns)


def test_abandoning_the_write_queue_finishes_the_element_in_hand_and_counts_the_rest_dropped() -> (
    None
):
    """A second Ctrl-C: what is queued is not written but counted, so the file's counts and
    the summary still add up."""
    writer = _HeldWriter()
    progress = Progress("cam/log", "generic")
    queue = WriteQueue(writer)  # type: ignore[arg-type]
    for t in range(1, 6):
        assert queue.put(progress, _element(t))
    assert writer.writing.wait(scaled(30))
    ender = threading.Thread(target=queue.abandon)
    ender.start()
    wait_until(lambda: queue.backlog() == (1, len(_element(1).payload) + len(_element(1).metadata)),
               30, "the queue to be emptied but for the element being written")  # fmt: skip
    writer.release.set()
    ender.join(scaled(30))
    assert not ender.is_alive()
    assert writer.written == [1]
    assert (progress.recorded, progress.dropped) == (1, 4)
    assert queue.backlog() == (0, 0)


def test_record_starts_recording_without_numpy_or_foxglove(tmp_path: Path) -> None:
    """What ``record camera/images gyro/rates`` runs before its recording starts: its
    module, the writer, the file with its channels."""
    script = (
        "import json, sys\n"
        "from pathlib import Path\n"
        "import services.cli.record\n"
        "from middleware import Retention\n"
        "from services.tools.bag import BagWriter, WriteQueue\n"
        f"w = BagWriter(Path({str(tmp_path / 'x.mcap')!r}))\n"
        f"for kind in {PLAIN_KINDS!r}:\n"
        "    w.add_buffer('s', kind, kind=kind, retention=Retention())\n"
        "WriteQueue(w).close()\n"
        "w.close()\n"
    )
    loaded = modules_after(script)
    heavy = sorted(m for m in loaded if m in HEAVY)
    assert heavy == [], f"record imported {heavy} before recording"
