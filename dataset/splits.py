"""Deterministic train/val/test splits by grasp, and leave-one-object-out.

Both fingers of a grasp look at the same contact, so a grasp is never split across
train and test. Grasps are ordered by a seeded SHA-256 of their key (object/grasp id) and
the ordered list is cut at 70 % and 85 %: the split depends only on the seed and the set of
grasps, not on the order samples were written in, and the proportions are exact up to
rounding even for small datasets.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence

from dataset.records import DatasetError, SampleRecord

SPLITS = ("train", "val", "test")
FRACTIONS = (0.70, 0.15, 0.15)


def _rank(key: str, seed: int) -> str:
    return hashlib.sha256(f"{seed}:{key}".encode()).hexdigest()


def split_grasps(grasp_keys: Sequence[str], seed: int) -> dict[str, str]:
    """Map each grasp key to "train", "val" or "test" (70/15/15 of the grasps)."""
    keys = sorted(set(grasp_keys), key=lambda k: (_rank(k, seed), k))
    n = len(keys)
    n_train = round(n * FRACTIONS[0])
    n_val = round(n * FRACTIONS[1])
    # With three or more grasps every split gets at least one: a test split must exist.
    if n >= 3:
        n_train = min(max(n_train, 1), n - 2)
        n_val = min(max(n_val, 1), n - n_train - 1)
    assignment = {}
    for i, key in enumerate(keys):
        assignment[key] = "train" if i < n_train else "val" if i < n_train + n_val else "test"
    return assignment


def split_records(records: Sequence[SampleRecord], seed: int) -> dict[str, list[SampleRecord]]:
    """The 70/15/15 split of samples by grasp, in manifest order within each split."""
    assignment = split_grasps([r.grasp_key for r in records], seed)
    out: dict[str, list[SampleRecord]] = {name: [] for name in SPLITS}
    for record in records:
        out[assignment[record.grasp_key]].append(record)
    return out


def leave_one_object_out(records: Sequence[SampleRecord], held_out: str, seed: int) -> dict[str, list[SampleRecord]]:
    """Test = every sample of ``held_out``; train/val = the other objects' grasps, 85/15."""
    objects = {r.object_name for r in records}
    if held_out not in objects:
        raise DatasetError(f"object {held_out!r} is not in the dataset (objects: {sorted(objects)})")
    rest = [r for r in records if r.object_name != held_out]
    if not rest:
        raise DatasetError(f"leaving out {held_out!r} leaves no training data")
    keys = sorted({r.grasp_key for r in rest}, key=lambda k: (_rank(k, seed), k))
    n_val = round(len(keys) * FRACTIONS[1] / (FRACTIONS[0] + FRACTIONS[1]))
    val_keys = set(keys[:n_val])
    return {
        "train": [r for r in rest if r.grasp_key not in val_keys],
        "val": [r for r in rest if r.grasp_key in val_keys],
        "test": [r for r in records if r.object_name == held_out],
    }
