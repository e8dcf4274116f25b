"""How the inference node (nodes.inference) runs a batch: the requests' regions laid into
forward passes, and its threads shared between the network and the input of the pass after."""

from __future__ import annotations

# Regions in one forward pass where the node's max_batch is 0 (its default), by device. On the
# CPU the next pass's input is cut and drawn during this pass, so a short pass keeps the
# pipeline's two stages in step: 64 regions cut from a cloud, 2 cores, the demo's model:
# 335-374 regions/s in passes of 8, 319-333 of 16, 263-292 of 32, the network alone the same
# (~575) at each. On a GPU the network wants wide passes (the lent H200's figures: 32).
DEVICE_MAX_BATCH = {"cpu": 8, "cuda": 32}


def max_batch_on(device: str, asked: int) -> int:
    """Regions in one forward pass on ``device``: ``asked``, or the device's own for 0."""
    return asked or DEVICE_MAX_BATCH[device]


def thread_split(threads: int, device: str, has_prior: bool) -> tuple[int, int]:
    """(the network's threads, the threads that cut and draw the next pass's input beside it)
    of a node given ``threads``. On the CPU, a model with a physics prior spends on a region's
    input (cut 0.8 ms, prior 0.55) a good part of its network's CPU (2.2 ms on one thread, 2.8 on
    two): each then keeps half the cores busy all the time, instead of both taking all of them
    in turn (64 regions cut from a cloud on 2 cores: 400-412 regions/s against 353-369; the
    network on both threads beside the input, or each pass's input and network on one thread in
    two lanes side by side, measured no better: docs/measurements.md). Otherwise the network has
    them all, and the input shares them."""
    if device == "cpu" and has_prior and threads >= 2:
        return threads - threads // 2, threads // 2
    return threads, threads


def forward_pass_parts(regions: list[int], max_batch: int) -> list[list[tuple[int, int, int]]]:
    """The requests' ``regions`` (a count each) in order, in forward passes of at most
    ``max_batch``: each pass the (request, first, stop) runs it holds (a pass may join two
    clients' regions, and a request may span passes)."""
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
