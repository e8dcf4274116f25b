"""Reading a dataset back: ``dataset.json``, the manifest, and each sample's files with
their checksums verified. The writer, resuming, reads through the same functions."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from dataset.codec import decode_npy, decode_png
from dataset.files import read_regular_file, sha256_hex
from dataset.images import check_rgb
from dataset.records import FILE_KINDS, DatasetError, DatasetInfo, Sample, SampleRecord

# Readers trust no file: sizes are bounded before anything is read or allocated.
_MAX_INFO_BYTES = 1 << 20
MAX_MANIFEST_BYTES = 256 << 20


def check_sample_arrays(
    info: DatasetInfo, tactile_rgb: np.ndarray, tactile_diff_rgb: np.ndarray, depth_map_m: np.ndarray, sample_id: str
) -> None:
    """A sample's arrays as ``info`` requires them: RGB images of its size, a float32 depth-map
    of the same size without -inf; DatasetError naming the sample otherwise."""
    shape = (info.image_height, info.image_width)
    for name, image in (("tactile", tactile_rgb), ("tactile_diff", tactile_diff_rgb)):
        image = check_rgb(image, f"sample {sample_id}: {name}")
        if image.shape[:2] != shape:
            raise DatasetError(f"sample {sample_id}: {name} is {image.shape[:2]}, dataset images are {shape}")
    depth = np.asarray(depth_map_m)
    if depth.dtype != np.float32 or depth.shape != shape:
        raise DatasetError(
            f"sample {sample_id}: depth-map must be {shape} float32 metres, got {depth.shape} {depth.dtype}"
        )
    if np.any(np.isneginf(depth)):
        raise DatasetError(f"sample {sample_id}: depth-map contains -inf (empty bins are NaN or +inf)")


def check_own_directories(root: Path) -> None:
    """The file directories must be the dataset's own: a symbolic link would read (or write)
    samples outside it."""
    for kind in FILE_KINDS:
        if (root / kind).is_symlink():
            raise DatasetError(f"{root / kind} is a symbolic link: a dataset holds its own files")


def read_info(path: Path) -> DatasetInfo:
    try:
        data = json.loads(read_regular_file(path, _MAX_INFO_BYTES, "dataset info"))
    except DatasetError:
        raise
    except FileNotFoundError as err:
        raise DatasetError(f"{path.parent} is not a dataset: {path.name} is missing") from err
    except (OSError, ValueError) as err:
        raise DatasetError(f"{path}: unreadable ({err})") from err
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: not a JSON object")
    return DatasetInfo.from_json(data)


def read_manifest(path: Path) -> list[SampleRecord]:
    try:
        text = read_regular_file(path, MAX_MANIFEST_BYTES, "manifest").decode("utf-8")
    except FileNotFoundError as err:
        raise DatasetError(f"{path.parent}: manifest.jsonl is missing") from err
    except (OSError, UnicodeDecodeError) as err:
        raise DatasetError(f"{path}: unreadable ({err})") from err
    if text and not text.endswith("\n"):
        raise DatasetError(
            f"{path}: last line is incomplete (a writer died mid-append; "
            "reopening the dataset with DatasetWriter repairs it)"
        )
    records = []
    for number, line in enumerate(text.splitlines(), start=1):
        try:
            records.append(SampleRecord.from_json(json.loads(line)))
        except (json.JSONDecodeError, DatasetError) as err:
            raise DatasetError(f"{path}:{number}: corrupt manifest line ({err})") from err
    return records


class DatasetReader:
    """Reads a dataset; ``load`` verifies the checksums of the files it reads."""

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"dataset directory {self.root} does not exist")
        self.info = read_info(self.root / "dataset.json")
        self.records = read_manifest(self.root / "manifest.jsonl")
        check_own_directories(self.root)
        self._by_id: dict[str, SampleRecord] = {}
        for record in self.records:
            if record.sample_id in self._by_id:
                raise DatasetError(f"{self.root}: sample {record.sample_id} appears twice in the manifest")
            self._by_id[record.sample_id] = record

    def __len__(self) -> int:
        return len(self.records)

    def __iter__(self) -> Iterator[Sample]:
        return (self.load(record) for record in self.records)

    def record(self, sample_id: str) -> SampleRecord:
        try:
            return self._by_id[sample_id]
        except KeyError as err:
            raise DatasetError(f"{self.root}: no sample {sample_id!r}") from err

    def load(self, sample: SampleRecord | str, verify: bool = True) -> Sample:
        record = self.record(sample) if isinstance(sample, str) else sample
        raw = {}
        shape = (self.info.image_height, self.info.image_width)
        limit = (1 << 20) + 8 * shape[0] * shape[1]  # an uncompressed PNG or .npy of this size, and then some
        for kind in FILE_KINDS:
            path = self.root / record.files[kind]
            try:
                raw[kind] = read_regular_file(path, limit, f"sample {record.sample_id}: file")
            except OSError as err:
                raise DatasetError(f"sample {record.sample_id}: cannot read {path} ({err})") from err
            if verify and sha256_hex(raw[kind]) != record.sha256[kind]:
                raise DatasetError(f"sample {record.sample_id}: checksum mismatch for {path}")
        sample_obj = Sample(
            record=record,
            tactile_rgb=decode_png(raw["tactile"], record.files["tactile"], shape),
            tactile_diff_rgb=decode_png(raw["tactile_diff"], record.files["tactile_diff"], shape),
            depth_map_m=decode_npy(raw["depth"], record.files["depth"], shape),
        )
        check_sample_arrays(
            self.info, sample_obj.tactile_rgb, sample_obj.tactile_diff_rgb, sample_obj.depth_map_m, record.sample_id
        )
        return sample_obj
