"""How the inference node lays a batch of requests into forward passes and shares its threads
(nodes.inference): every region once, in order, no pass over max_batch."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from nodes.inference_passes import forward_pass_parts, thread_split


@given(regions=st.lists(st.integers(1, 40), min_size=1, max_size=6), max_batch=st.integers(1, 33))
def test_passes_hold_every_region_once_in_order_and_are_full_but_the_last(regions: list[int], max_batch: int) -> None:
    passes = forward_pass_parts(regions, max_batch)
    sizes = [sum(stop - first for _, first, stop in parts) for parts in passes]
    assert all(size == max_batch for size in sizes[:-1]) and 1 <= sizes[-1] <= max_batch
    laid = [(request, k) for parts in passes for request, first, stop in parts for k in range(first, stop)]
    assert laid == [(request, k) for request, count in enumerate(regions) for k in range(count)]
    assert all(first < stop for parts in passes for _, first, stop in parts)


@given(threads=st.integers(1, 64))
def test_a_prior_on_the_cpu_gets_half_the_threads_beside_the_network(threads: int) -> None:
    network, inputs = thread_split(threads, "cpu", has_prior=True)
    assert network + inputs == max(threads, 2) and network >= inputs >= 1 and network - inputs <= 1
    assert thread_split(threads, "cpu", has_prior=False) == (threads, threads)
    assert thread_split(threads, "cuda", has_prior=True) == (threads, threads)
