"""How the inference node (nodes.inference) runs a batch: the requests' regions laid into
forward passes, and its threads shared between the passes and their input."""

from __future__ import annotations

import dataclasses

import numpy as np

# Regions in one forward pass where the node's max_batch is 0 (its default), by device. On the
# CPU, measured while the next passes' input was drawn beside the network (before each lane
# drew its own), short passes kept the two in step: 64 regions cut from a cloud, 2 cores, the
# demo's model, in two lanes: 349-397 regions/s in passes of 8, 329-354 of 16, 371-390 of 4
# (one pass at a time: 335-374 of 8, 263-292 of 32). On a GPU every pass costs kernel launches
# and a trip back, so a request is one pass: a lent H100, three YCB clouds, 256 poses: 1,565-2,023
# regions/s in passes of 256, 1,217-1,770 of 64 or 128, 1,243-1,351 of 32 (64 poses: 1,450-1,567
# against 958-1,434 of 32).
DEVICE_MAX_BATCH = {"cpu": 8, "cuda": 256}
# A node serving the prior on the CPU runs no network: a pass is its cut, prior and uncertainty in
# one lane. Measured before a small batch was spread over the lanes (forward_pass_parts), a
# 64-region request ran 1,077 and 1,153 regions/s in passes of 32, 974 and 1,029 of 16, 605 and 635
# of 64 (one lane idle). Spread, passes of 64 and of 32 lay such a request alike (1,092 and 1,094);
# at 256 poses 1,074 against 929, within the runs' spread (`dtx bench serve --points --poses 64 256
# --max-batch N`, 2 cores, the demo's model, 2026-11-29).
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
    """How an inference node spends its ``threads``: passes side by side (``lanes``), each
    computing on ``lane_threads``. ``input_in_lanes``: each lane cuts and draws its own pass's
    input before serving it; else the batch's own thread draws the next passes' input on
    ``input_threads`` while the lanes serve the passes before."""

    lanes: int
    lane_threads: int
    input_threads: int
    input_in_lanes: bool


def thread_split(threads: int, device: str) -> ThreadSplit:
    """The node's threads on ``device``. On the CPU each thread is a lane that serves whole
    passes, its cut, prior, network and uncertainty one after another: the network is cheapest a
    region on one thread (2.2 ms CPU against 2.8 on two, the demo's model, passes of 8; alone, two
    such lanes ran 861-898 regions/s where one pass on both cores ran 531-566), and the stages'
    own parallel forms left cores idle between them (the cut, then the prior, each on both
    threads, the bus thread laying out the images): one planner's 64-pose request took 68 ms
    against 59 now (docs/measurements.md, 2026-11-29). On a GPU one pass at a time on all the threads, the
    next passes' input drawn on the host's threads meanwhile."""
    if device == "cpu":
        return ThreadSplit(lanes=threads, lane_threads=1, input_threads=1, input_in_lanes=True)
    return ThreadSplit(lanes=1, lane_threads=threads, input_threads=threads, input_in_lanes=False)


def forward_pass_parts(regions: list[int], max_batch: int, lanes: int = 1) -> list[list[tuple[int, int, int]]]:
    """The requests' ``regions`` (a count each) in order, in forward passes of at most
    ``max_batch`` and, where fewer would leave some of ``lanes`` idle, of ceil(regions / lanes)
    (two planners' 32 depth-maps each, 2 cores, one pass at a time: 1,240-1,406 regions/s): each
    pass the (request, first, stop) runs it holds (a pass may join two clients' regions, and a
    request may span passes). ValueError for a ``max_batch`` or ``lanes`` that is not an integer
    >= 1 (a pass of no room would never end the laying) or a count below 0."""
    if not (_is_integer(max_batch) and max_batch >= 1):
        raise ValueError(f"max_batch must be an integer >= 1 (regions in one forward pass), got {_shown(max_batch)}")
    if not (_is_integer(lanes) and lanes >= 1):
        raise ValueError(f"lanes must be an integer >= 1 (passes side by side), got {_shown(lanes)}")
    for request, count in enumerate(regions):
        if not (_is_integer(count) and count >= 0):
            raise ValueError(f"regions[{request}] must be a count (an integer >= 0), got {_shown(count)}")
    width = max(1, min(int(max_batch), -(-sum(regions) // lanes)))
    passes: list[list[tuple[int, int, int]]] = [[]]
    room = width
    for request, count in enumerate(regions):
        first = 0
        while first < count:
            if room == 0:
                passes.append([])
                room = width
            stop = min(count, first + room)
            passes[-1].append((request, first, stop))
            room -= stop - first
            first = stop
    return passes


@dataclasses.dataclass(frozen=True)
class ServedRegions:
    """What a batch's regions are answered with, in request order, each lane writing its passes'
    rows: the reply's images (N x H x W x 3 uint8), their u (N x H x W float32 levels) and each
    region's mean u, or None for a checkpoint without the uncertainty. Written in place, not
    joined from the passes: a 64-region request's 4.5 MB copied once less, in the lanes rather
    than after them."""

    images: np.ndarray
    uncertainty: np.ndarray | None
    region_uncertainty: np.ndarray

    @staticmethod
    def empty(regions: int, size: int, uncertainty: bool) -> "ServedRegions":
        """Room for ``regions`` size x size answers, with their u where ``uncertainty``."""
        u = np.empty((regions, size, size), np.float32) if uncertainty else None
        return ServedRegions(np.empty((regions, size, size, 3), np.uint8), u, np.empty(regions))
