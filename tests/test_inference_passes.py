"""How the inference node lays a batch of requests into forward passes and shares its threads
(nodes.inference): every region once, in order, no pass over max_batch."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from nodes.inference_passes import (
    DEVICE_MAX_BATCH,
    PRIOR_SERVING_CPU_MAX_BATCH,
    ThreadSplit,
    forward_pass_parts,
    max_batch_on,
    thread_split,
)


@given(
    regions=st.lists(st.integers(1, 40), min_size=1, max_size=6),
    max_batch=st.integers(1, 33),
    lanes=st.integers(1, 8),
)
def test_passes_hold_every_region_once_in_order_and_are_full_but_the_last(
    regions: list[int], max_batch: int, lanes: int
) -> None:
    passes = forward_pass_parts(regions, max_batch, lanes)
    width = min(max_batch, -(-sum(regions) // lanes))
    sizes = [sum(stop - first for _, first, stop in parts) for parts in passes]
    assert all(size == width for size in sizes[:-1]) and 1 <= sizes[-1] <= width
    laid = [(request, k) for parts in passes for request, first, stop in parts for k in range(first, stop)]
    assert laid == [(request, k) for request, count in enumerate(regions) for k in range(count)]
    assert all(first < stop for parts in passes for _, first, stop in parts)
    # No lane idle while another holds two passes, unless max_batch bounds them.
    assert len(passes) <= lanes or width == max_batch


@given(threads=st.integers(1, 64))
def test_on_the_cpu_each_thread_is_a_lane_drawing_its_own_input(threads: int) -> None:
    assert thread_split(threads, "cpu") == ThreadSplit(
        lanes=threads, lane_threads=1, input_threads=1, input_in_lanes=True
    )
    assert thread_split(threads, "cuda") == ThreadSplit(
        lanes=1, lane_threads=threads, input_threads=threads, input_in_lanes=False
    )


def test_a_cpu_node_serving_its_prior_takes_longer_passes_unless_told() -> None:
    assert max_batch_on("cpu", 0) == DEVICE_MAX_BATCH["cpu"] == 8
    assert max_batch_on("cpu", 0, network=False) == PRIOR_SERVING_CPU_MAX_BATCH == 32
    assert max_batch_on("cuda", 0, network=False) == max_batch_on("cuda", 0) == DEVICE_MAX_BATCH["cuda"]
    assert max_batch_on("cpu", 5, network=False) == max_batch_on("cpu", 5) == 5
