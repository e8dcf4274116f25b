"""How the inference node (nodes.inference) runs a batch: the requests' regions laid into
forward passes, and its threads shared between the passes and the input of the passes after."""

from __future__ import annotations

import dataclasses

import numpy as np

# Regions in one forward pass where the node's max_batch is 0 (its default), by device. On the
# CPU the next passes' input is cut and drawn while the network runs, so short passes keep the
# two in step: 64 regions cut from a cloud, 2 cores, the demo's model, in two lanes: 349-397
# regions/s in passes of 8, 329-354 of 16, 371-390 of 4 (one pass at a time: 335-374 of 8,
# 263-292 of 32). On a GPU every pass costs kernel launches and a trip back, so a request is one
# pass: a lent H100, three YCB clouds, 256 poses: 1,565-2,023 regions/s in passes of 256, 1,217-1,770
# of 64 or 128, 1,243-1,351 of 32 (64 poses: 1,450-1,567 against 958-1,434 of 32).
DEVICE_MAX_BATCH = {"cpu": 8, "cuda": 256}
# A node serving the prior on the CPU runs no network: a pass is its uncertainty alone (0.4 ms a
# region), and longer passes leave its input threads fewer waits: 64 regions cut from a cloud, 2
# cores, 374-406 regions/s in passes of 32, 380 of 64, 318-332 of 8 (2026-11-29, the same hour).
PRIOR_SERVING_CPU_MAX_BATCH = 32


def max_batch_on(device: str, asked: int, network: bool = True) -> int:
    """Regions in one pass on ``device``: ``asked``, or for 0 the device's own
    (PRIOR_SERVING_CPU_MAX_BATCH where a CPU node serves the prior, no ``network``). ValueError
    naming ``device`` (one of DEVICE_MAX_BATCH) or ``max_batch`` (an integer >= 0)."""
    if not (isinstance(device, str) and device in DEVICE_MAX_BATCH):
        raise ValueError(f"device must be one of {sorted(DEVICE_MAX_BATCH)}, got {_shown(device)}")
    if not (_is_integer(asked) and asked >= 0):
        raise ValueError(f"max_batch must be an integer >= 0 (0: the device's own), got {_shown(asked)}")
    own = PRIOR_SERVING_CPU_MAX_BATCH if device == "cpu" and not network else DEVICE_MAX_BATCH[device]
    return int(asked) or own


def _is_integer(value: object) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _shown(value: object) -> str:
    """``value`` for an error message, bounded (an int past 4,300 digits has no repr at all)."""
    if isinstance(value, int) and value.bit_length() > 64:
        return f"an integer of {value.bit_length()} bits"
    return repr(value)[:80]


@dataclasses.dataclass(frozen=True)
class ThreadSplit:
    """How an inference node spends its ``threads``: forward passes side by side (``lanes``),
    each computing on ``lane_threads``, while the batch's own thread cuts and draws the next
    passes' input on ``input_threads``."""

    lanes: int
    lane_threads: int
    input_threads: int


def thread_split(threads: int, device: str, network: bool = True) -> ThreadSplit:
    """The node's threads on ``device``. On the CPU the network is cheapest a region on one
    thread (2.2 ms CPU against 2.8 on two, the demo's model, passes of 8), so each core runs a
    pass of its own: alone, two such lanes ran 861-898 regions/s where one pass on both cores ran
    531-566. The input (cut 0.8 ms a region, prior 0.55) is drawn meanwhile on half of them:
    one thread draws the prior's images, whose many short NumPy calls do not run two at a time
    (2 cores, through the bus: cloud form 349-397 regions/s at 64 poses against 318-365 with one
    pass at a time, depth-maps 449-541 against 333-384; docs/measurements.md). Serving the prior
    (``network`` false), a pass is the uncertainty alone, a tenth of the input's work: the input
    is drawn on every thread. On a GPU one pass at a time, the host's threads for the input."""
    if device == "cpu":
        return ThreadSplit(
            lanes=threads, lane_threads=1, input_threads=threads if not network else max(1, threads // 2)
        )
    return ThreadSplit(lanes=1, lane_threads=threads, input_threads=threads)


def forward_pass_parts(regions: list[int], max_batch: int) -> list[list[tuple[int, int, int]]]:
    """The requests' ``regions`` (a count each) in order, in forward passes of at most
    ``max_batch``: each pass the (request, first, stop) runs it holds (a pass may join two
    clients' regions, and a request may span passes). ValueError for a ``max_batch`` that is not
    an integer >= 1 (no pass would have room: the laying would never end) or a count below 0."""
    if not (_is_integer(max_batch) and max_batch >= 1):
        raise ValueError(f"max_batch must be an integer >= 1 (regions in one forward pass), got {_shown(max_batch)}")
    for request, count in enumerate(regions):
        if not (_is_integer(count) and count >= 0):
            raise ValueError(f"regions[{request}] must be a count (an integer >= 0), got {_shown(count)}")
    passes: list[list[tuple[int, int, int]]] = [[]]
    room = max_batch
    for request, count in enumerate(regions):
        first = 0
        while first < count:
            if room == 0:
                passes.append([])
                room = max_batch
            stop = min(count, first + room)
            passes[-1].append((request, first, stop))
            room -= stop - first
            first = stop
    return passes
