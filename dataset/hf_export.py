"""Export sessions in the Hugging Face Hub's own layout, which ``datasets.load_dataset(DIR)`` reads
without a loading script::

    DIR/README.md                                  dataset card: YAML front matter + text (dataset.hf_card)
    DIR/data/{train,validation,test}-NNNNN-of-MMMMM.parquet

One row a pair: the tactile image and its background difference (PNG, ``datasets.Image``), the
depth-map (float32 ``Array2D``, metres, bit for bit), the grasp and the poses (float64, as the
manifest holds them), the object, the finger and the session. The splits are the project's, as
``dtx train`` makes them of the same sessions (``dataset.splits.split_sessions``: one session, its
own split; ``val`` is called ``validation``); a split without pairs is left out, as ``datasets``
cannot load an empty one. The directory is written beside ``DIR`` and renamed into place
(``dataset.out_dir``) once it has been read back with ``datasets.load_dataset`` and found to hold
every pair.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import datasets
import numpy as np
from datasets.arrow_writer import ParquetWriter

from dataset.check import records_checksum
from dataset.codec import encode_png
from dataset.hf_card import SessionSummary, dataset_card
from dataset.out_dir import check_apart, write_directory
from dataset.reader import DatasetReader
from dataset.records import DatasetError, SampleRecord
from dataset.splits import SPLITS, session_fingerprint, split_sessions
from msgs.progress import Progress

HF_SPLITS = {"train": "train", "val": "validation", "test": "test"}
# A shard holds at most this many bytes of raw arrays (the Hub's viewer takes shards of a few
# hundred MB); a row group 100 rows, as ``datasets`` writes image datasets.
SHARD_BYTES = 256 << 20
ROW_GROUP_ROWS = 100
# What the sessions of one export must share, as the sessions one model learns from do
# (models.sessions): the pairs' size, the depth range and what a bin holds. Each keeps its crop.
_SHARED = ("image_height", "image_width", "depth_range_m", "depth_map_method")


@dataclasses.dataclass(frozen=True)
class _Session:
    name: str
    reader: DatasetReader
    fingerprint: str
    checksum: str
    splits: dict[str, list[SampleRecord]]  # by Hugging Face split name


def hf_features(height: int, width: int) -> datasets.Features:
    """The columns of an export of ``height`` x ``width`` pairs."""
    pose = datasets.Array2D(shape=(4, 4), dtype="float64")
    return datasets.Features(
        {
            "sample_id": datasets.Value("string"),
            "session": datasets.Value("string"),
            "object": datasets.Value("string"),
            "grasp_id": datasets.Value("int64"),
            "finger": datasets.Value("string"),
            "tactile": datasets.Image(),
            "tactile_diff": datasets.Image(),
            "depth_map_m": datasets.Array2D(shape=(height, width), dtype="float32"),
            "grasp_pose_world": datasets.List(datasets.Value("float64"), length=4),
            "gel_to_world": pose,
            "model_to_world": pose,
            "model_to_gel": pose,
            "registration_fitness": datasets.Value("float64"),
        }
    )


def export_hf(
    roots: Sequence[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    force: bool = False,
    progress: bool = False,
    shard_bytes: int = SHARD_BYTES,
) -> dict[str, int]:
    """Write the sessions at ``roots`` to ``out`` (replacing an existing one only with ``force``);
    returns the pairs per split as read back. DatasetError for a directory that is not a dataset,
    sessions that cannot be mixed, a sample whose files do not match its manifest."""
    if not roots:
        raise DatasetError("no session to export")
    check_apart(out, roots)
    return write_directory(out, force, lambda staging: _write(staging, _open_sessions(roots), progress, shard_bytes))


def _open_sessions(roots: Sequence[str | os.PathLike[str]]) -> list[_Session]:
    """The sessions, refused unless they can be mixed; split as ``dtx train`` splits them
    (dataset.splits.split_sessions ordered by fingerprint: one session, its own split)."""
    readers = [DatasetReader(root) for root in roots]
    first = readers[0]
    for reader in readers[1:]:
        for field in _SHARED:
            if getattr(reader.info, field) != getattr(first.info, field):
                raise DatasetError(
                    f"{reader.root} cannot be exported with {first.root}: its {field} is "
                    f"{getattr(reader.info, field)}, not {getattr(first.info, field)}"
                )
    checksums = [records_checksum(reader) for reader in readers]
    for i, checksum in enumerate(checksums):
        if checksum in checksums[:i]:
            twin = readers[checksums.index(checksum)].root
            raise DatasetError(f"{readers[i].root} holds the same pairs as {twin}: give each session once")
    fingerprints = [session_fingerprint(reader.root) for reader in readers]
    splits = split_sessions(
        [reader.records for reader in readers], [reader.info.split_seed for reader in readers], "", fingerprints
    )
    names = [reader.root.resolve().name for reader in readers]
    return [
        _Session(
            name=f"{name}-{fingerprint[:8]}" if names.count(name) > 1 else name,
            reader=reader,
            fingerprint=fingerprint,
            checksum=checksum,
            splits={HF_SPLITS[split]: records for split, records in split.items()},
        )
        for name, reader, fingerprint, checksum, split in zip(
            names, readers, fingerprints, checksums, splits, strict=True
        )
    ]


def _write(staging: Path, sessions: list[_Session], progress: bool, shard_bytes: int) -> dict[str, int]:
    info = sessions[0].reader.info
    features = hf_features(info.image_height, info.image_width)
    row_bytes = info.image_height * info.image_width * (4 + 3 + 3)  # depth-map, two images
    rows_per_shard = max(1, shard_bytes // row_bytes)
    (staging / "data").mkdir()
    pairs = {split: [(s, record) for s in sessions for record in s.splits[split]] for split in HF_SPLITS.values()}
    with Progress("exporting pairs", sum(map(len, pairs.values())), "pairs", enabled=progress) as shown:
        for split, rows in pairs.items():
            shards = math.ceil(len(rows) / rows_per_shard)
            for shard in range(shards):
                path = staging / "data" / f"{split}-{shard:05d}-of-{shards:05d}.parquet"
                _write_shard(path, features, rows[shard * rows_per_shard : (shard + 1) * rows_per_shard], shown)
    summaries = [
        SessionSummary(
            name=s.name,
            fingerprint=s.fingerprint,
            checksum=s.checksum,
            info=s.reader.info,
            objects=tuple(sorted({r.object_name for r in s.reader.records})),
            counts={split: len(records) for split, records in s.splits.items()},
        )
        for s in sessions
    ]
    (staging / "README.md").write_text(dataset_card(features, summaries))
    return read_back(staging, {split: len(rows) for split, rows in pairs.items() if rows}, features)


def _write_shard(
    path: Path, features: datasets.Features, pairs: list[tuple[_Session, SampleRecord]], shown: Progress
) -> None:
    """One Parquet file of ``pairs``, in row groups of ROW_GROUP_ROWS."""
    writer = ParquetWriter(features=features, path=str(path))
    try:
        for start in range(0, len(pairs), ROW_GROUP_ROWS):
            rows = [_row(session, record) for session, record in pairs[start : start + ROW_GROUP_ROWS]]
            writer.write_batch({name: [row[name] for row in rows] for name in rows[0]})
            shown.update(len(rows))
        writer.finalize()
    finally:
        writer.close()


def _row(session: _Session, record: SampleRecord) -> dict[str, Any]:
    """One pair as a row; its files' checksums are verified as they are read."""
    sample = session.reader.load(record)
    return {
        "sample_id": record.sample_id,
        "session": session.name,
        "object": record.object_name,
        "grasp_id": record.grasp_id,
        "finger": record.finger,
        "tactile": {"bytes": encode_png(sample.tactile_rgb), "path": None},
        "tactile_diff": {"bytes": encode_png(sample.tactile_diff_rgb), "path": None},
        "depth_map_m": sample.depth_map_m,
        "grasp_pose_world": list(record.grasp_pose),
        "gel_to_world": _matrix(record.gel_to_world),
        "model_to_world": _matrix(record.model_to_world),
        "model_to_gel": _matrix(record.model_to_gel),
        "registration_fitness": record.registration_fitness,
    }


def _matrix(value: tuple[tuple[float, ...], ...] | None) -> np.ndarray | None:
    return None if value is None else np.array(value, dtype=np.float64)


def read_back(directory: Path, expected: dict[str, int], features: datasets.Features) -> dict[str, int]:
    """Load ``directory`` as ``datasets.load_dataset`` does, into a cache deleted afterwards;
    DatasetError unless it has exactly the ``expected`` pairs per split and ``features``."""
    bars = datasets.is_progress_bar_enabled()
    datasets.disable_progress_bars()
    try:
        with tempfile.TemporaryDirectory(prefix="dtx-hf-read-back.") as cache:
            loaded = datasets.load_dataset(str(directory), cache_dir=cache)
            counts = {name: loaded[name].num_rows for name in loaded}
            wrong = [name for name in loaded if loaded[name].features != features]
    finally:
        if bars:
            datasets.enable_progress_bars()
    if counts != expected or wrong:
        raise DatasetError(
            f"{directory} read back with datasets.load_dataset holds {counts} pairs"
            + (f" with other columns in {wrong}" if wrong else "")
            + f", written {expected}"
        )
    return {name: counts[name] for name in (HF_SPLITS[s] for s in SPLITS) if name in counts}
