"""A peer that answers one ``@info`` query with many large replies: whoever asked reads them
one at a time and keeps a bounded few, never all of them (real processes, real Zenoh)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import pytest
import zenoh

from middleware._decode import MAX_REPLY_BYTES
from middleware._wire import Keys
from tests.conftest import run_python
from tests.helpers.raw_zenoh import answering, flooding_session

pytestmark = pytest.mark.integration

KEYS = Keys("framegate")
REPLIES = 250  # of MAX_REPLY_BYTES each: ~1 GB, were it all held

# A framegate command, then its peak RSS (kB) on its own last line of stderr.
_MEASURED = """
import resource, sys
from services.cli import _main
code = _main(sys.argv[1:])
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)
sys.exit(code)
"""


@contextmanager
def _reply_bomb(endpoint: str) -> Iterator[None]:
    """A peer offering ``evil`` that answers every ``@info`` query with ``REPLIES`` replies
    of the largest size a description may have (none of them a valid description)."""
    blob = zenoh.ZBytes(b"{" + b" " * (MAX_REPLY_BYTES - 2) + b"}")

    def replies(key: str) -> list[tuple[str, zenoh.ZBytes]]:
        return [(key.replace("*", f"evil{i}"), blob) for i in range(REPLIES)]

    with flooding_session(endpoint, listen=True) as rogue:
        with answering(rogue, KEYS.info("*"), replies, [KEYS.service_token("evil")]):
            yield


@pytest.mark.parametrize("command", [["info", "evil"], ["ls"]], ids=["info", "ls"])
def test_a_flood_of_large_replies_to_info_is_not_held(endpoint: str, command: list[str]) -> None:
    """250 replies of 4 MiB to one ``@info`` query: ``info`` and ``ls`` grew to 1.3 GB
    holding every reply before looking at any; now each is read as it comes, so the
    process holds a short channel of them, and says what was wrong in one line."""
    with _reply_bomb(endpoint):
        done = run_python(["-c", _MEASURED, *command, "--connect", endpoint], timeout_s=120)
    *said, peak = done.stderr.strip().splitlines()
    assert "Traceback" not in done.stderr, done.stderr
    peak_mb = int(peak) / 1024
    # Below all of them held once (1,062-1,072 MB when every reply was held before any was
    # read). Alone it peaks at 80-210 MB (16 waiting replies, one decoded, the interpreter);
    # beside the rest of the suite on 2 cores, 755-771 MB were measured (where that memory
    # sits, in Zenoh or the allocator, is not established; docs/limits.md).
    assert peak_mb < REPLIES * MAX_REPLY_BYTES / 2**20, f"peak RSS {peak_mb:.0f} MB"
    assert said and all(line.startswith(("error:", "warning: left out")) for line in said), said
