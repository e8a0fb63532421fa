"""Independent random streams derived from the scenario seed.

Each use (bumps, gyro, textures, per-frame sensor noise) has its own stream, so rendering
frames in any order, or only some of them, gives the same bytes.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np


class Stream(IntEnum):
    """Which random stream; the value is part of the seed, so never renumber."""

    BUMPS = 1
    GYRO = 2
    TEXTURE = 3
    FRAME_NOISE = 4
    SHARP_NOISE = 5


def rng_for(seed: int, stream: Stream, *index: int) -> np.random.Generator:
    """A generator for one stream (and e.g. one frame) of one seed."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(stream), *index]))
