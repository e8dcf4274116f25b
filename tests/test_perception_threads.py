"""The kernels' kept pool (perception.threads): every share done once, on the caller and the
pool side by side, errors raised, the pool kept between calls and made anew in a forked child."""

from __future__ import annotations

import multiprocessing
import threading

import pytest

from perception import threads
from perception.threads import run_shares


def test_every_share_runs_once_the_first_on_the_calling_thread() -> None:
    done: dict[tuple[int, int], str] = {}

    def work(first: int, stop: int) -> None:
        done[(first, stop)] = threading.current_thread().name

    shares = [(0, 3), (3, 5), (5, 9)]
    run_shares(work, shares)
    assert sorted(done) == shares
    assert done[(0, 3)] == threading.current_thread().name
    assert all(name.startswith("dtx-kernel") for share, name in done.items() if share != (0, 3))
    run_shares(work, [])  # nothing to do: nothing done


def test_the_pool_is_kept_between_calls() -> None:
    run_shares(lambda first, stop: None, [(0, 1), (1, 2)])
    kept = threads._kept_pool()
    run_shares(lambda first, stop: None, [(0, 1), (1, 2)])
    assert threads._kept_pool() is kept


@pytest.mark.parametrize("failing", [(0, 1), (1, 2)])
def test_an_error_in_any_share_is_raised_after_every_share_ended(failing: tuple[int, int]) -> None:
    ended: list[tuple[int, int]] = []

    def work(first: int, stop: int) -> None:
        if (first, stop) == failing:
            raise ValueError(f"share {first}..{stop}")
        ended.append((first, stop))

    with pytest.raises(ValueError, match=f"share {failing[0]}..{failing[1]}"):
        run_shares(work, [(0, 1), (1, 2), (2, 3)])
    assert sorted(ended) == sorted({(0, 1), (1, 2), (2, 3)} - {failing})


def _shares_in_child(queue: multiprocessing.Queue) -> None:
    done: list[tuple[int, int]] = []
    run_shares(lambda first, stop: done.append((first, stop)), [(0, 1), (1, 2), (2, 3)])
    queue.put(sorted(done))


def test_a_forked_child_runs_its_shares_on_a_pool_of_its_own() -> None:
    run_shares(lambda first, stop: None, [(0, 1), (1, 2)])  # the parent's pool has threads
    context = multiprocessing.get_context("fork")
    queue = context.Queue()
    child = context.Process(target=_shares_in_child, args=(queue,))
    child.start()
    child.join(60)
    assert child.exitcode == 0
    assert queue.get(timeout=5) == [(0, 1), (1, 2), (2, 3)]
