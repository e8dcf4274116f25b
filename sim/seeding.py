"""Random draws keyed on what they simulate, so a session is a function of its seed.

A simulated sensor frame's noise and the arm's repeatability error come from a generator
seeded by (the world's seed, a stream number, a digest of what is simulated: the state a frame
shows, the target a move was sent to), not from a stream that advances once per frame. Which
frame a node happens to take then does not change what it sees: two sessions with the same
seed, or a session resumed after a crash, register on the same depth frames, press the same
gels and write the same dataset (``dtx dataset checksum``).

What this gives up: frames of an unchanging state repeat their noise where a real sensor's
would not (nothing in the pipeline averages frames), and the arm returning to a target lands
where it landed before. An effect that is a process over frames (the GelSight's
``lighting_drift`` walk) still follows the frame count, so a scene that calls for it is not
reproducible frame for frame.
"""

from __future__ import annotations

import hashlib

import numpy as np

__all__ = ["state_rng"]


def state_rng(state: bytes | np.ndarray, seed: int, *streams: int) -> np.random.Generator:
    """The generator of one simulated draw: the same (state bytes, seed, streams) give the same
    draws in any process; any difference in them gives independent ones. ``state``: bytes or an
    array, hashed in place when C-contiguous (a frame's gap map is not copied per frame)."""
    # An array's bytes are hashed through its buffer (``.data``, a memoryview), not a copy.
    data = np.ascontiguousarray(state).data if isinstance(state, np.ndarray) else state
    digest = np.frombuffer(hashlib.blake2b(data, digest_size=16).digest(), dtype=np.uint32)
    return np.random.default_rng([int(seed), *(int(s) for s in streams), *digest.tolist()])
