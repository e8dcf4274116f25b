"""Deterministic train/val/test splits by grasp, and leave-one-object-out.

Both fingers of a grasp look at the same contact, so a grasp is never split across
train and test. Grasps are ordered by a seeded SHA-256 of their key (object/grasp id) and
the ordered list is cut at 70 % and 85 %: the split depends only on the seed and the set of
grasps, not on the order samples were written in, and the proportions are exact up to
rounding even for small datasets.

Several sessions (days of collection, each with its own calibration) are split together by
:func:`split_sessions`: each session keeps its own split, and a grasp that repeats another
session's (:func:`twin_grasps`: same object, the gel within TWIN_MM and TWIN_DEG of where it
was) joins that grasp's split, so that no contact is learnt in one session and tested in another.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dataset.records import DatasetError, SampleRecord

SPLITS = ("train", "val", "test")
FRACTIONS = (0.70, 0.15, 0.15)
# Two grasps of one object in different sessions are the same contact when the gel was this
# near where it was (translation, mm) and turned this little (degrees).
TWIN_MM = 1.0
TWIN_DEG = 2.0


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
    return {**_train_val(rest, seed), "test": [r for r in records if r.object_name == held_out]}


def _train_val(records: Sequence[SampleRecord], seed: int) -> dict[str, list[SampleRecord]]:
    """Train/val of ``records`` by grasp, 85/15 (leave-one-object-out's objects left in)."""
    keys = sorted({r.grasp_key for r in records}, key=lambda k: (_rank(k, seed), k))
    n_val = round(len(keys) * FRACTIONS[1] / (FRACTIONS[0] + FRACTIONS[1]))
    val_keys = set(keys[:n_val])
    return {
        "train": [r for r in records if r.grasp_key not in val_keys],
        "val": [r for r in records if r.grasp_key in val_keys],
    }


def _gel_poses(records: Sequence[SampleRecord]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per record: where the gel was on the object (model_to_gel: translation mm, rotation; zeros
    where unknown), whether that is known, and the grasp pose (x, y, z mm; theta_z rad)."""
    known = np.array([r.model_to_gel is not None for r in records])
    m2g = np.array([np.asarray(r.model_to_gel) if r.model_to_gel is not None else np.eye(4) for r in records])
    grasp = np.array([r.grasp_pose for r in records], dtype=np.float64).reshape(-1, 4)
    grasp[:, :3] *= 1e3
    return m2g[:, :3, 3] * 1e3, m2g[:, :3, :3], known, grasp


def _near(a: Sequence[SampleRecord], b: Sequence[SampleRecord]) -> np.ndarray:
    """len(a) x len(b): which pairs hold the gel at the same place on the object (see
    :func:`twin_grasps`)."""
    ta, ra, ka, ga = _gel_poses(a)
    tb, rb, kb, gb = _gel_poses(b)
    cos_turn = (np.einsum("aij,bij->ab", ra, rb) - 1.0) / 2.0  # cos of the angle of ra^T rb
    on_model = (np.linalg.norm(ta[:, None] - tb[None], axis=-1) <= TWIN_MM) & (cos_turn >= np.cos(np.radians(TWIN_DEG)))
    turn = np.angle(np.exp(1j * (ga[:, None, 3] - gb[None, :, 3])))
    in_world = (np.linalg.norm(ga[:, None, :3] - gb[None, :, :3], axis=-1) <= TWIN_MM) & (
        np.abs(turn) <= np.radians(TWIN_DEG)
    )
    return np.where(ka[:, None] & kb[None], on_model, in_world)


def twin_grasps(sessions: Sequence[Sequence[SampleRecord]]) -> list[tuple[tuple[int, str], tuple[int, str]]]:
    """Grasps of different sessions that touch the same contact, as pairs of (session index,
    grasp key). The rule: same object, and a finger of each whose gel pose is within TWIN_MM
    (translation) and TWIN_DEG (rotation) of the other's; the gel pose is where the gel was on
    the object (``model_to_gel``) when both samples record it, the grasp pose in world
    (x, y, z, theta_z) otherwise. Within a session, a grasp's fingers share its key (as today)."""
    twins = []
    for i, first in enumerate(sessions):
        for j in range(i + 1, len(sessions)):
            for name in sorted({r.object_name for r in first} & {r.object_name for r in sessions[j]}):
                a = [r for r in first if r.object_name == name]
                b = [r for r in sessions[j] if r.object_name == name]
                for ia, ib in zip(*np.nonzero(_near(a, b))):
                    twins.append(((i, a[ia].grasp_key), (j, b[ib].grasp_key)))
    return twins


def _session_split(records: Sequence[SampleRecord], seed: int, held_out: str) -> dict[str, list[SampleRecord]]:
    """One session's part of :func:`split_sessions`, before twins are joined."""
    if not held_out:
        return split_records(records, seed)
    test = [r for r in records if r.object_name == held_out]
    rest = [r for r in records if r.object_name != held_out]
    return {**(_train_val(rest, seed) if rest else {"train": [], "val": []}), "test": test}


def split_sessions(
    sessions: Sequence[Sequence[SampleRecord]], seeds: Sequence[int], held_out: str = "", order: Sequence[str] = ()
) -> list[dict[str, list[SampleRecord]]]:
    """The splits of several sessions' records, one dict a session (``seeds``: each session's
    split seed). Each session is split as alone (:func:`split_records`, or with ``held_out``
    :func:`leave_one_object_out`, a session without that object 85/15 into train/val); then
    every group of twin grasps (:func:`twin_grasps`, joined transitively) takes the split of
    its first grasp by (``order`` of its session, default its index; grasp key), so that no
    contact, nor a grasp's two fingers, is on both sides. ``order``: a per-session key that
    does not depend on the order sessions are given in (their fingerprints)."""
    if held_out and not any(r.object_name == held_out for records in sessions for r in records):
        objects = sorted({r.object_name for records in sessions for r in records})
        raise DatasetError(f"object {held_out!r} is in none of the sessions (objects: {objects})")
    splits = [_session_split(records, seed, held_out) for records, seed in zip(sessions, seeds)]
    assigned = {(i, r.grasp_key): name for i, split in enumerate(splits) for name in SPLITS for r in split[name]}
    parent = {node: node for node in assigned}

    def root(node: tuple[int, str]) -> tuple[int, str]:
        while parent[node] != node:
            node = parent[node]
        return node

    keys = order or [f"{i:06d}" for i in range(len(sessions))]
    for a, b in twin_grasps(sessions):
        ra, rb = sorted((root(a), root(b)), key=lambda n: (keys[n[0]], n[1]))
        parent[rb] = ra
    out: list[dict[str, list[SampleRecord]]] = [{name: [] for name in SPLITS} for _ in sessions]
    for i, records in enumerate(sessions):
        for record in records:
            out[i][assigned[root((i, record.grasp_key))]].append(record)
    return out


def session_fingerprint(root: Path) -> str:
    """SHA-256 of ``dataset.json`` and the manifest, 16 hex digits: what a checkpoint records of a
    session it learnt from (models.sessions), and the order that ties several sessions' splits."""
    digest = hashlib.sha256()
    for name in ("dataset.json", "manifest.jsonl"):
        digest.update((root / name).read_bytes())
    return digest.hexdigest()[:16]
