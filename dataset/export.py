"""Export to the aligned A|B format of the reference pix2pix implementation.

``OUT/{train,val,test}/<sample_id>.png``: one RGB image 2W wide, A (the depth-map,
normalised with the dataset's depth_range_m to [-1, 1], written as grey 0..255 with near =
dark) on the left, B (the tactile image) on the right; train there with ``--direction AtoB``
(``--input_nc 1`` to read A as one channel).
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from dataset.reader import DatasetReader
from dataset.records import DatasetError
from dataset.splits import SPLITS, split_records
from perception.normalisation import normalise_depth_map


def depth_to_grey(depth_map_m: np.ndarray, depth_range_m: tuple[float, float]) -> np.ndarray:
    """H x W metres -> H x W x 3 uint8 grey image of the normalised depth-map."""
    normalised = normalise_depth_map(depth_map_m, depth_range_m)
    grey = np.round((normalised + 1.0) * 127.5).astype(np.uint8)
    return np.repeat(grey[:, :, None], 3, axis=2)


def export_pix2pix(root: str | os.PathLike[str], out: str | os.PathLike[str]) -> dict[str, int]:
    """Write the A|B images of every sample into ``out``; returns the count per split."""
    reader = DatasetReader(root)
    out_dir = Path(out)
    counts = {}
    for name, records in split_records(reader.records, reader.info.split_seed).items():
        split_dir = out_dir / name
        split_dir.mkdir(parents=True, exist_ok=True)
        for record in records:
            sample = reader.load(record)
            a = depth_to_grey(sample.depth_map_m, reader.info.depth_range_m)
            pair = np.concatenate([a, sample.tactile_rgb], axis=1)
            path = split_dir / f"{record.sample_id}.png"
            if not cv2.imwrite(str(path), cv2.cvtColor(pair, cv2.COLOR_RGB2BGR)):
                raise DatasetError(f"could not write {path}")
        counts[name] = len(records)
    return {name: counts[name] for name in SPLITS}
