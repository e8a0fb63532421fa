"""An LD_PRELOAD shim that shifts one process's wall clock, and only that.

``CLOCK_REALTIME`` (and ``gettimeofday``, ``time``) read through the shim return the real
time plus an offset in ns; ``CLOCK_MONOTONIC`` is untouched, as when NTP/chrony steps the
system clock. The offset comes from a file (re-read every 10 ms, so a test can step the
clock of a running process) or, without one, from an environment variable::

    lib = build_clock_shim(tmp_path)
    offset = tmp_path / "offset"
    offset.write_text(str(-5 * 10**9))
    env = shifted_clock_env(child_env(), lib, offset)      # start the process with env
    step_clock(offset, -7 * 10**9)                          # later: a step while it runs
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

OFFSET_FILE_ENV = "SHIM_REALTIME_OFFSET_FILE"
OFFSET_NS_ENV = "SHIM_REALTIME_OFFSET_NS"

_SOURCE = r"""
#define _GNU_SOURCE
#include <dlfcn.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/time.h>
#include <time.h>

typedef int (*clock_gettime_fn)(clockid_t, struct timespec *);
static clock_gettime_fn real_clock_gettime;
static long long cached_offset;
static long long next_read_ns = -1;

static long long mono_ns(void) {
    struct timespec ts;
    real_clock_gettime(CLOCK_MONOTONIC, &ts);
    return (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static long long offset_ns(void) {
    if (!real_clock_gettime)
        real_clock_gettime = (clock_gettime_fn)dlsym(RTLD_NEXT, "clock_gettime");
    long long now = mono_ns();
    if (next_read_ns >= 0 && now < next_read_ns)
        return cached_offset;
    long long value = 0;
    const char *file = getenv("SHIM_REALTIME_OFFSET_FILE");
    if (file) {
        FILE *f = fopen(file, "r");
        if (f) {
            if (fscanf(f, "%lld", &value) != 1) value = cached_offset;
            fclose(f);
        } else {
            value = cached_offset;
        }
    } else {
        const char *env = getenv("SHIM_REALTIME_OFFSET_NS");
        value = env ? atoll(env) : 0;
    }
    cached_offset = value;
    next_read_ns = now + 10000000LL;
    return value;
}

static void shift(struct timespec *ts, long long by) {
    long long ns = (long long)ts->tv_sec * 1000000000LL + ts->tv_nsec + by;
    ts->tv_sec = ns / 1000000000LL;
    ts->tv_nsec = ns % 1000000000LL;
    if (ts->tv_nsec < 0) { ts->tv_nsec += 1000000000LL; ts->tv_sec -= 1; }
}

int clock_gettime(clockid_t id, struct timespec *ts) {
    if (!real_clock_gettime)
        real_clock_gettime = (clock_gettime_fn)dlsym(RTLD_NEXT, "clock_gettime");
    int rc = real_clock_gettime(id, ts);
    if (rc == 0 && (id == CLOCK_REALTIME || id == CLOCK_REALTIME_COARSE))
        shift(ts, offset_ns());
    return rc;
}

int gettimeofday(struct timeval *tv, void *tz) {
    struct timespec ts;
    (void)tz;
    clock_gettime(CLOCK_REALTIME, &ts);
    if (tv) { tv->tv_sec = ts.tv_sec; tv->tv_usec = ts.tv_nsec / 1000; }
    return 0;
}

time_t time(time_t *out) {
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    if (out) *out = ts.tv_sec;
    return ts.tv_sec;
}
"""


def build_clock_shim(directory: Path) -> Path:
    """Compile the shim into ``directory``; the shared library's path."""
    gcc = shutil.which("gcc")
    if gcc is None:
        import pytest

        pytest.skip("gcc is needed to build the clock shim")
    source = directory / "clock_shim.c"
    library = directory / "clock_shim.so"
    source.write_text(_SOURCE)
    subprocess.run(
        [gcc, "-shared", "-fPIC", "-O2", "-o", str(library), str(source), "-ldl"],
        check=True,
        capture_output=True,
    )
    return library


def shifted_clock_env(env: dict[str, str], library: Path, offset_file: Path) -> dict[str, str]:
    """``env`` for a process whose wall clock is shifted by the ns in ``offset_file``."""
    out = dict(env)
    preload = out.get("LD_PRELOAD", "")
    out["LD_PRELOAD"] = f"{library} {preload}".strip()
    out[OFFSET_FILE_ENV] = str(offset_file)
    return out


def step_clock(offset_file: Path, offset_ns: int) -> None:
    """Set the shifted processes' offset (they see it within about 10 ms)."""
    tmp = offset_file.with_suffix(".tmp")
    tmp.write_text(str(offset_ns))
    tmp.replace(offset_file)
