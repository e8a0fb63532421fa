"""A peer that answers a service's own ``@info`` key with a flood of replies while the
service starts (its one-producer-per-name check, ``_service._instances``) and while a
subscriber asks who may refuse it (``answering_sessions``): both read through the bounded
``@info`` intake, so the service starts, answers, and holds a bounded few of the replies
(real processes, real Zenoh)."""

from __future__ import annotations

import pytest
import zenoh

from middleware._decode import MAX_REPLY_BYTES
from middleware._wire import Keys
from tests.conftest import run_python
from tests.helpers.raw_zenoh import answering, flooding_session

pytestmark = pytest.mark.integration

KEYS = Keys("framegate")
REPLIES = 250  # of MAX_REPLY_BYTES each, per query: ~1 GB, were it all held

# A service ``victim`` started beside the flood; then who answers as it (the session ids a
# subscriber trusts), its own session id, and its peak RSS (kB), one a line.
_VICTIM = """
import resource, sys
from middleware import NetworkConfig, Node
from middleware._service import answering_sessions
with Node("victim", NetworkConfig(connect=(sys.argv[1],))) as node:
    node.offer("b")
    print(",".join(sorted(answering_sessions(node._session, node.keys, "victim"))))
    print(node._session.info.zid())
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def test_a_reply_flood_on_a_services_own_info_key_is_not_held(endpoint: str) -> None:
    """250 replies of 4 MiB to each of the starting service's ``@info`` queries: read
    through Zenoh's default channel (256 replies, each held whole until read and decoded)
    the service took 3.9 s to start and peaked at 545 MB; now each reply is kept or counted
    as it comes, at most ``MAX_DESCRIPTIONS`` (16 MiB in all) of them, so it starts, finds
    its own session the one answering as it, and stays far below."""
    blob = zenoh.ZBytes(b"{" + b" " * (MAX_REPLY_BYTES - 2) + b"}")
    replies = [(KEYS.info("victim"), blob)] * REPLIES
    with (
        flooding_session(endpoint, listen=True) as rogue,
        answering(rogue, KEYS.info("victim"), lambda _key: replies),
    ):
        done = run_python(["-c", _VICTIM, endpoint], timeout_s=120)
    assert done.returncode == 0, done.stderr
    answering_ids, own_id, peak = done.stdout.split()
    assert answering_ids == own_id  # the garbage answers count for no one
    peak_mb = int(peak) / 1024
    # Alone: 545 MB before, 78 MB now (one query's replies could be held; now 16 MiB of them
    # at most, and Zenoh's own receive buffers). But what Zenoh's buffers hold in flight
    # grows as the process gets less CPU: a clean-clone suite at a load of 5 peaked at 551
    # MB, as much as before. So the bound here is only the class (never the whole flood
    # held: memory bounded by the intake, not by the peer); the figure is measured, not
    # asserted (docs/limits.md).
    assert peak_mb < REPLIES * MAX_REPLY_BYTES / 2**20, f"peak RSS {peak_mb:.0f} MB"
