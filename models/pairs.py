"""Training pairs streamed from their sessions' files: memory bounded by a stated cache, not by
the number of pairs.

A :class:`PairSet` is the pairs of one split over a lab's sessions and contact libraries, in
order (each session's records, then each library's samples). A batch of indices is made from
the files where its pairs are not cached (models.data: depth input, physics prior, target):
the same tensors, bit for bit, as loading every pair at once. Pairs made are kept, packed, until
the cache holds ``cache_mib``; past it the rest are made again each time they are drawn (the
session's files read again, checksums verified, and the prior rendered), so ten sessions train
in the memory of one and a half. Packed, a pair is its depth channels in float32 and its prior
image and target as 0..255 levels (uint8): exact, since both are levels / 127.5 - 1 in float32.

Under ``torchrun`` each rank makes only the pairs of its own batches: no rank reads every session.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from typing import Protocol

import numpy as np
import torch
from torch.utils.data import Dataset

from dataset.reader import DatasetReader
from dataset.records import SampleRecord
from models.data import image_target, load_samples, moved_in_gel_plane, network_input
from models.networks import GeneratorConfig, ModelConfigError
from models.prior import PhysicsPrior

MIB = 2**20


class PairSource(Protocol):
    """Pairs of one session or library, made from its files on demand."""

    def __len__(self) -> int: ...

    def make(self, indices: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Network input and target (N x C x H x W, N x 3 x H x W) of the pairs at ``indices``."""
        ...


@dataclasses.dataclass(frozen=True)
class SessionPairs:
    """A session's ``records``, each depth-map's prior blurred by the session's pose error
    ``pose_sigma_mm`` (None: the prior's default)."""

    reader: DatasetReader
    records: Sequence[SampleRecord]
    config: GeneratorConfig
    prior: PhysicsPrior | None
    pose_sigma_mm: float | None = None

    def __len__(self) -> int:
        return len(self.records)

    def make(self, indices: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        maps, images = load_samples(self.reader, [self.records[i] for i in indices])
        x = network_input(maps, self.reader.info.depth_range_m, self.config, self.prior, self.pose_sigma_mm)
        return x, image_target(images)


@dataclasses.dataclass(frozen=True)
class LibraryPairs:
    """Every sample of a contact library (dataset.contact_library): exact geometry with a sharp
    prior, or, given ``sigmas_mm`` and ``offsets_mm`` (one a sample), each depth-map moved in the
    gel plane by its offset (models.data.moved_in_gel_plane) with its prior rendered at its sigma."""

    reader: DatasetReader
    config: GeneratorConfig
    prior: PhysicsPrior | None
    sigmas_mm: np.ndarray | None = None
    offsets_mm: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.reader.records)

    def make(self, indices: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        maps, images = load_samples(self.reader, [self.reader.records[i] for i in indices])
        info = self.reader.info
        sigmas: float | np.ndarray = 0.0
        if self.sigmas_mm is not None and self.offsets_mm is not None:
            if info.depth_crop_m is None:
                raise ModelConfigError(
                    f"{self.reader.root} does not record its depth crop, which moving its maps needs"
                )
            maps = moved_in_gel_plane(maps, self.offsets_mm[indices], info.depth_crop_m, info.depth_range_m[1])
            sigmas = self.sigmas_mm[indices]
        return network_input(maps, info.depth_range_m, self.config, self.prior, sigmas), image_target(images)


def _to_levels(images: torch.Tensor) -> torch.Tensor:
    """Images in [-1, 1] that are levels / 127.5 - 1 -> those levels, uint8."""
    return ((images.cpu() + 1.0) * 127.5).round().to(torch.uint8)


def _from_levels(levels: torch.Tensor) -> torch.Tensor:
    return levels.float() / 127.5 - 1.0


Packed = tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # depth channels, prior levels, target levels


class PairCache:
    """Packed pairs kept up to ``mib`` MiB, shared by the sets that draw on it (train and
    validation): filled as pairs are first made, never evicted (with the epochs' random order,
    any kept pair is as likely to be drawn again as another)."""

    def __init__(self, mib: float) -> None:
        if not np.isfinite(mib) or mib < 0:
            raise ModelConfigError(f"the pair cache must be a finite size >= 0 MiB, got {mib}")
        self.capacity_bytes, self.used_bytes = int(mib * MIB), 0
        self._pairs: dict[tuple[int, int], Packed] = {}

    def __len__(self) -> int:
        return len(self._pairs)

    def get(self, key: tuple[int, int]) -> Packed | None:
        return self._pairs.get(key)

    def offer(self, key: tuple[int, int], pair: Packed) -> None:
        """Keep ``pair`` if the cache has room for it."""
        size = sum(t.nbytes for t in pair)
        if self.used_bytes + size <= self.capacity_bytes:
            self._pairs[key], self.used_bytes = pair, self.used_bytes + size


class PairSet(Dataset[tuple[torch.Tensor, torch.Tensor]]):
    """The pairs of ``sources`` in order, made on demand and kept in ``cache`` (module
    docstring); batches on ``device``. ``depth_channels``: the input's channels before the
    prior's image (the generator's in_channels)."""

    def __init__(
        self,
        sources: Sequence[PairSource],
        depth_channels: int,
        cache: PairCache,
        device: torch.device = torch.device("cpu"),
    ) -> None:
        self.sources, self.depth_channels, self.cache, self.device = list(sources), depth_channels, cache, device
        sizes = [len(source) for source in self.sources]
        self._source = np.repeat(np.arange(len(sizes)), sizes)
        self._local = np.concatenate([np.arange(n) for n in sizes]) if sizes else np.zeros(0, np.int64)

    def __len__(self) -> int:
        return len(self._source)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        x, y = self.batch([index])
        return x[0], y[0]

    def batch(self, indices: Sequence[int] | np.ndarray | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Input and target of the pairs at ``indices``, in that order, on this set's device."""
        wanted = np.asarray(indices.cpu() if isinstance(indices, torch.Tensor) else indices, dtype=np.int64)
        if wanted.size and (wanted.min() < 0 or wanted.max() >= len(self)):
            raise IndexError(f"pair indices must be in [0, {len(self)}), got {wanted.min()}..{wanted.max()}")
        packed: dict[int, Packed] = {}
        for i in map(int, wanted):
            pair = self.cache.get(self._key(i))
            if pair is not None:
                packed[i] = pair
        packed |= self._make(np.array(sorted(set(map(int, wanted)) - set(packed)), dtype=np.int64))
        x = torch.stack([torch.cat([packed[i][0], _from_levels(packed[i][1])]) for i in map(int, wanted)])
        y = torch.stack([_from_levels(packed[i][2]) for i in map(int, wanted)])
        return x.to(self.device), y.to(self.device)

    def _key(self, index: int) -> tuple[int, int]:
        return id(self.sources[self._source[index]]), int(self._local[index])

    def _make(self, indices: np.ndarray) -> dict[int, Packed]:
        """The pairs at ``indices`` made from their sources, packed, and offered to the cache."""
        made = {}
        for source in np.unique(self._source[indices]):
            chosen = indices[self._source[indices] == source]
            x, y = self.sources[source].make(self._local[chosen])
            for i, xi, yi in zip(map(int, chosen), x.cpu(), y.cpu()):
                made[i] = (xi[: self.depth_channels].clone(), _to_levels(xi[self.depth_channels :]), _to_levels(yi))
                self.cache.offer(self._key(i), made[i])
        return made

    def chunks(self, size: int = 64) -> list[np.ndarray]:
        """Every index, in order, in chunks of at most ``size``."""
        return [np.arange(start, min(start + size, len(self))) for start in range(0, len(self), size)]

    def tensors(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Every pair at once (for sets a caller has bounded: :meth:`subset`)."""
        if not len(self):
            raise ModelConfigError("no pairs to load")
        parts = [self.batch(chunk) for chunk in self.chunks()]
        return torch.cat([x for x, _ in parts]), torch.cat([y for _, y in parts])

    def subset(self, count: int, seed: int) -> PairSet:
        """At most ``count`` of these pairs in their order, drawn seeded by ``seed`` where there
        are more (this set itself where there are not), sharing this set's sources and cache."""
        if len(self) <= count:
            return self
        kept = np.sort(np.random.default_rng(seed).choice(len(self), count, replace=False))
        chosen = PairSet(self.sources, self.depth_channels, self.cache, self.device)
        chosen._source, chosen._local = self._source[kept], self._local[kept]
        return chosen

    def mean_target(self) -> torch.Tensor:
        """The mean target image (3 x H x W, [-1, 1]) over every pair, summed in float64."""
        total = torch.zeros((), dtype=torch.float64)
        for chunk in self.chunks():
            total = total + self.batch(chunk)[1].double().sum(dim=0)
        return (total / len(self)).float().to(self.device)


def library_pairs(
    libraries: Sequence[str | os.PathLike[str]],
    sessions: Sequence[DatasetReader],
    config: GeneratorConfig,
    prior: PhysicsPrior | None,
    pose_sigma_range_mm: tuple[float, ...] = (),
    seed: int = 0,
) -> list[LibraryPairs]:
    """Each library dataset (dataset.contact_library) as pairs, refused unless its depth-maps are
    every session's (method, range and crop). A library's geometry is exact: its prior is sharp,
    unless ``pose_sigma_range_mm`` (low, high) asks for the uncertainties a model must answer
    for; then each pair gets a sigma drawn uniformly in it (seeded by ``seed``) and an in-plane
    offset drawn from that sigma's Gaussian: a registration that far off, saying so, with the
    tactile image of where the contact really was."""
    rng = np.random.default_rng(seed)
    chosen = []
    for library in libraries:
        reader = DatasetReader(library)
        for session in sessions:
            _check_library(library, reader, session)
        if not pose_sigma_range_mm:
            chosen.append(LibraryPairs(reader, config, prior))
            continue
        if reader.info.depth_crop_m is None:
            raise ModelConfigError(f"{reader.root} does not record its depth crop, which moving its maps needs")
        sigmas = rng.uniform(pose_sigma_range_mm[0], pose_sigma_range_mm[1], len(reader.records))
        offsets = rng.standard_normal((len(reader.records), 2)) * sigmas[:, None]
        chosen.append(LibraryPairs(reader, config, prior, sigmas, offsets))
    return chosen


def _check_library(library: str | os.PathLike[str], reader: DatasetReader, session: DatasetReader) -> None:
    """ModelConfigError unless the library at ``library`` (``reader``) cuts its depth-maps as ``session``."""
    if reader.info.depth_map_method != session.info.depth_map_method:
        raise ModelConfigError(
            f"library {library} holds {reader.info.depth_map_method} depth-maps, the dataset "
            f"{session.info.depth_map_method} ones: make it with the session's (dtx dataset library --depth-map)"
        )
    for name in ("depth_range_m", "depth_crop_m"):
        mine, theirs = getattr(reader.info, name), getattr(session.info, name)
        if mine is not None and theirs is not None and not np.allclose(mine, theirs, rtol=0, atol=1e-9):
            raise ModelConfigError(
                f"library {library} has {name} {mine}, the dataset {theirs}: make it "
                "with the session's settings (dtx dataset library --depth-range-m)"
            )
