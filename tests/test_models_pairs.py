"""Training pairs streamed from the sessions' files (models.pairs): bit for bit the pairs loaded
at once, in memory bounded by the stated cache, each rank reading only its own share."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from test_models_pose_sigma_range import PRIOR, SCENE  # the tiny prior generator and its scene

from dataset.contact_library import write_contact_library
from dataset.reader import DatasetReader
from models.checkpoint import TrainConfig, load_checkpoint
from models.data import load_pairs, session_prior
from models.networks import ModelConfigError
from models.pairs import PairCache, PairSet, SessionPairs, library_pairs
from models.sessions import load_training_data, open_sessions, session_records
from models.train import _Dist, _epoch_batches, build_state, train

TINY = TrainConfig(epochs=2, epochs_decay=0, batch_size=4, ndf=8, threads=1, session_pose_sigma_mm=1.0, generator=PRIOR)


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A dataset with a scene and a depth crop (a contact library is one), so pairs carry a prior."""
    return write_contact_library(tmp_path_factory.mktemp("pairs") / "session", 24, seed=3, scene=SCENE).root


def _pairs(root: Path, cache_mib: float, sigma_mm: float = 1.0) -> tuple[PairSet, DatasetReader]:
    reader = DatasetReader(root)
    prior = session_prior(reader, PRIOR, sigma_mm)
    return PairSet(
        [SessionPairs(reader, reader.records, PRIOR, prior)], PRIOR.in_channels, PairCache(cache_mib)
    ), reader


def _count_loads(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    loaded: list[str] = []
    load = DatasetReader.load

    def counted(self: DatasetReader, record: object) -> object:
        loaded.append(record.sample_id)  # type: ignore[attr-defined]
        return load(self, record)  # type: ignore[arg-type]

    monkeypatch.setattr(DatasetReader, "load", counted)
    return loaded


@pytest.mark.parametrize("cache_mib", [0.0, 1.0, 64.0])  # nothing, about ten pairs, all of them
def test_streamed_pairs_are_the_pairs_loaded_at_once_bit_for_bit(session: Path, cache_mib: float) -> None:
    pairs, reader = _pairs(session, cache_mib)
    expected = load_pairs(reader, None, PRIOR, session_prior(reader, PRIOR, 1.0))
    order = np.random.default_rng(0).permutation(len(pairs))
    for _ in range(2):  # made, then (where it had room) from the cache
        for batch in np.array_split(order, 7):
            x, y = pairs.batch(batch)
            assert torch.equal(x, expected[0][batch]) and torch.equal(y, expected[1][batch])
    x, y = pairs[5]
    assert torch.equal(x, expected[0][5]) and torch.equal(y, expected[1][5])


def test_the_cache_holds_at_most_its_size_and_spares_the_files_what_it_holds(
    session: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    loaded = _count_loads(monkeypatch)
    small, _ = _pairs(session, 0.5)
    small.tensors()
    assert 0 < small.cache.used_bytes <= 0.5 * 2**20 and 0 < len(small.cache) < len(small)
    kept = len(small.cache)
    loaded.clear()
    small.tensors()
    assert len(loaded) == len(small) - kept  # what the cache holds is not read again
    everything, _ = _pairs(session, 64.0)
    everything.tensors()
    loaded.clear()
    everything.tensors()
    assert loaded == []
    nothing, _ = _pairs(session, 0.0)
    nothing.tensors()
    assert len(nothing.cache) == 0 and nothing.cache.used_bytes == 0


def test_a_library_streams_moved_as_registered_the_same_as_at_once(session: Path) -> None:
    reader = DatasetReader(session)
    prior = session_prior(reader, PRIOR)
    sources = library_pairs([session], [reader], PRIOR, prior, (0.5, 1.5), seed=4)
    whole = PairSet(sources, PRIOR.in_channels, PairCache(0)).tensors()
    streamed = PairSet(
        library_pairs([session], [reader], PRIOR, prior, (0.5, 1.5), seed=4), PRIOR.in_channels, PairCache(0)
    )
    for batch in np.array_split(np.random.default_rng(1).permutation(len(streamed)), 5):
        x, y = streamed.batch(batch)
        assert torch.equal(x, whole[0][batch]) and torch.equal(y, whole[1][batch])
    moved = PairSet(
        library_pairs([session], [reader], PRIOR, prior, (), seed=4), PRIOR.in_channels, PairCache(0)
    ).tensors()
    assert not torch.equal(moved[0], whole[0])  # the range moved the maps


def test_a_subset_is_seeded_in_order_and_bounded(session: Path) -> None:
    pairs, _ = _pairs(session, 0.0)
    chosen = pairs.subset(10, seed=0)
    assert len(chosen) == 10 and pairs.subset(len(pairs), seed=0) is pairs
    again = pairs.subset(10, seed=0)
    assert torch.equal(chosen.tensors()[1], again.tensors()[1])
    assert not torch.equal(chosen.tensors()[1], pairs.subset(10, seed=1).tensors()[1])
    whole = pairs.tensors()[1]
    rows = [next(i for i in range(len(pairs)) if torch.equal(whole[i], y)) for y in chosen.tensors()[1]]
    assert rows == sorted(rows)


def test_training_is_the_same_whatever_the_cache(session: Path, tmp_path: Path) -> None:
    """The cache changes what is read and when, never what is learnt: the same weights, bit for bit."""
    weights = []
    for cache_mib in (0.0, 0.5, 512.0):
        config = dataclasses.replace(TINY, pair_cache_mib=cache_mib)
        path = train(session, config, tmp_path / f"cache{cache_mib}", progress=False, libraries=[session])
        weights.append(load_checkpoint(path)["generator"])
    for other in weights[1:]:
        assert all(torch.equal(other[k], v) for k, v in weights[0].items())


def test_each_rank_reads_only_its_own_share(session: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    config = dataclasses.replace(TINY, pair_cache_mib=0.0)
    shares = []
    for rank in (0, 1):
        state = build_state(session, config, dist=_Dist(rank=rank, world=2))
        loaded = _count_loads(monkeypatch)
        for index in _epoch_batches(state, 0):
            state.train.batch(index)
        shares.append(set(loaded))
        monkeypatch.undo()
        assert len(loaded) == state.per_rank
    assert not shares[0] & shares[1]


@pytest.mark.parametrize("size", [-1.0, float("nan"), float("inf")])
def test_a_cache_of_no_size_is_refused(size: float) -> None:
    with pytest.raises(ModelConfigError, match="pair_cache_mib must be a finite number of MiB >= 0"):
        dataclasses.replace(TINY, pair_cache_mib=size).validate()
    with pytest.raises(ModelConfigError, match="finite size >= 0 MiB"):
        PairCache(size)


def test_indices_outside_the_set_are_refused(session: Path) -> None:
    pairs, _ = _pairs(session, 0.0)
    with pytest.raises(IndexError, match=rf"\[0, {len(pairs)}\)"):
        pairs.batch([0, len(pairs)])
    with pytest.raises(IndexError):
        pairs.batch([-1])


def test_each_session_keeps_its_own_pose_uncertainty(session: Path, tmp_path: Path) -> None:
    """Two sessions of one scene, one redepthed with a touch calibration and one not: each
    session's pairs get the prior blurred by its own pose error, and the checkpoint says which."""
    other = write_contact_library(tmp_path / "other", 12, seed=9, scene=SCENE).root
    config = dataclasses.replace(TINY, session_pose_sigmas_mm=(0.0, 2.0))
    train_pairs, _, meta = load_training_data([session, other], config, (), torch.device("cpu"))
    readers = [DatasetReader(root) for root in (session, other)]
    chosen = session_records(open_sessions([session, other]), "train")
    expected = [
        load_pairs(reader, records, PRIOR, session_prior(reader, PRIOR, sigma))[0]
        for reader, records, sigma in zip(readers, chosen, (0.0, 2.0))
    ]
    assert torch.equal(train_pairs.tensors()[0], torch.cat(expected))
    assert [entry["pose_sigma_mm"] for entry in meta["sessions"]] == [0.0, 2.0]
    with pytest.raises(ModelConfigError, match="3 pose uncertainties given for 2 sessions"):
        load_training_data(
            [session, other], dataclasses.replace(TINY, session_pose_sigmas_mm=(0.0, 1.0, 2.0)), (), torch.device("cpu")
        )
    with pytest.raises(ModelConfigError, match="session_pose_sigmas_mm must be a finite number"):
        dataclasses.replace(TINY, session_pose_sigmas_mm=(0.0, -1.0)).validate()
