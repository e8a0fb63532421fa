"""``query-scaling``: a range query returning k elements from buffers of n elements.

framegate: ``Node.query(target, time_range="[a..b]")`` selecting exactly k elements from the
middle of a buffer of n small elements (the series is bisected, so the latency must not grow
with n). raw: ``session.get`` answered by a callback queryable with k replies of the same
size. Latency is the median of back-to-back queries; for each k, the raw run comes first,
then one framegate run that queries the buffers of every n in turn, so all n share the same
moment of a shared machine.
"""

from __future__ import annotations

from ._options import BenchOptions
from ._procs import WorkerGroup, free_endpoint
from ._records import Goal, Row, ScenarioResult
from ._stats import percentile, ratio

ELEMENT_BYTES = 64
FULL_COUNTS = (1_000, 10_000, 100_000)
QUICK_COUNTS = (1_000, 10_000)
FULL_KS = (1, 100, 1_000)
QUICK_KS = (1, 100)
GOAL_K = 100
SCALING_GOAL = 2.0
MAX_QUERIES = 5_000


def _power(n: int) -> str:
    exponent = len(str(n)) - 1
    return f"10^{exponent}" if n == 10**exponent else str(n)


def run_query_scaling(options: BenchOptions) -> ScenarioResult:
    counts = QUICK_COUNTS if options.quick else FULL_COUNTS
    ks = QUICK_KS if options.quick else FULL_KS
    window_s = max(0.2, options.duration_s / 4)
    result = ScenarioResult(
        "query-scaling",
        params={
            "counts": list(counts),
            "ks": list(ks),
            "element_bytes": ELEMENT_BYTES,
            "window_s_per_combination": window_s,
            "raw": "session.get -> k replies from a callback queryable (no buffer, so no n)",
            "framegate": "Node.query(time_range=[a..b]) selecting k elements mid-buffer, "
            "the n buffers queried in turn",
        },
    )
    rows = {
        (n, k): Row(f"k={k} from n={_power(n)}", "query p50", "us", higher_is_better=False)
        for n in counts
        for k in ks
        if k <= n
    }
    raw_at, fg_at = free_endpoint(), free_endpoint()
    with WorkerGroup() as group:
        group.start("raw-queryable", {"listen": raw_at})
        raw_client = group.start("raw-querier", {"connect": raw_at})
        server = group.start("fg-query-server", {"listen": fg_at, "counts": list(counts)})
        fg_client = group.start("fg-query-client", {"connect": fg_at})
        group.wait_ready(timeout_s=300.0)
        result.params["fill_s"] = server.ready.get("fill_s")
        for pair in range(options.pairs):
            for k in ks:
                sizes = [n for n in counts if k <= n]
                raw = _summary(
                    raw_client.call(
                        "latency",
                        timeout_s=window_s + 60,
                        seconds=window_s,
                        size=ELEMENT_BYTES,
                        k=k,
                        max_count=MAX_QUERIES,
                    )["latencies_us"],
                    pair,
                )
                answer = fg_client.call(
                    "latency",
                    timeout_s=window_s * len(sizes) + 60,
                    seconds=window_s * len(sizes),
                    ns=sizes,
                    k=k,
                    max_count=MAX_QUERIES,
                )
                for n in sizes:
                    row = rows[(n, k)]
                    assert row.raw is not None
                    row.raw.append(raw)
                    row.framegate.append(_summary(answer["latencies_us"][str(n)], pair))
                    options.progress(
                        f"query-scaling {row.name} pair {pair + 1}/{options.pairs}: "
                        f"raw {raw['value']:.0f} us, framegate {row.framegate[-1]['value']:.0f} us"
                    )
    for row in rows.values():
        row.note = "raw has no buffer: each n shows the same raw samples of its k"
    smallest, largest = rows.get((counts[0], GOAL_K)), rows.get((counts[-1], GOAL_K))
    if smallest is not None and largest is not None:
        largest.goal = Goal(
            f"k={GOAL_K}: n={_power(counts[-1])} <= {SCALING_GOAL:g}x n={_power(counts[0])}",
            SCALING_GOAL,
            False,
            ratio(largest.median("framegate"), smallest.median("framegate")),
        )
    result.rows = list(rows.values())
    return result


def _summary(latencies_us: list[float], pair: int) -> dict[str, float]:
    return {
        "pair": pair,
        "value": percentile(latencies_us, 50),
        "p99": percentile(latencies_us, 99),
        "count": len(latencies_us),
    }
