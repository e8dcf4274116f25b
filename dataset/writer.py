"""Writing a dataset: samples appended crash-safely, resumed where a run stopped.

Crash safety: every file of a sample goes to a temporary name, is fsynced and renamed into
place; only then is the manifest line appended and fsynced. A sample therefore exists
exactly when its manifest line does. Files left without a manifest line by a crash are
overwritten when the sample is written again on resume. A torn last manifest line (the
process died mid-append) is cut off when a writer reopens the dataset.

A grasp's fingers land together: ``write_together`` writes every file of both samples first
and then appends their manifest lines in one write, so a crash at any point leaves both or
neither. Should an append still be torn between the lines, ``drop_incomplete_grasps`` (a
collector resuming) removes the lone finger so the whole grasp is redone.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dataset.codec import encode_npy, encode_png
from dataset.files import fsync_dir, read_regular_file, sha256_hex, write_atomic
from dataset.reader import MAX_MANIFEST_BYTES, check_own_directories, check_sample_arrays, read_info, read_manifest
from dataset.records import (
    FILE_KINDS,
    FINGERS,
    SAMPLE_ID,
    DatasetError,
    DatasetInfo,
    EncodedSample,
    SampleRecord,
    rigid_transform_tuple,
    sample_files,
)


def _info_mismatch(root: Path, stored: DatasetInfo, given: DatasetInfo) -> str:
    """Why a dataset cannot be resumed with ``given``: each field that differs from ``stored``,
    and what to do (a resumed dataset must be one dataset: one normalisation, one scene, one code)."""
    fields = [f.name for f in dataclasses.fields(DatasetInfo) if getattr(stored, f.name) != getattr(given, f.name)]
    differences = "; ".join(f"{name} {getattr(stored, name)!r} there, {getattr(given, name)!r} now" for name in fields)
    return (
        f"{root}: dataset.json holds another dataset than this run makes ({differences}); "
        "to make it again remove the directory or write to another one"
    )


class DatasetWriter:
    """Appends samples to a dataset directory; reopening an existing dataset resumes it.

    ``info`` is required for a new dataset; for an existing one it may be omitted, and if
    given must equal what is stored (one dataset, one normalisation and one scene).
    """

    def __init__(self, root: str | os.PathLike[str], info: DatasetInfo | None = None) -> None:
        self.root = Path(root)
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            for kind in FILE_KINDS:
                (self.root / kind).mkdir(exist_ok=True)
            check_own_directories(self.root)
            meta_path = self.root / "dataset.json"
            if meta_path.exists():
                stored = read_info(meta_path)
                if info is not None and info != stored:
                    raise DatasetError(_info_mismatch(self.root, stored, info))
                self.info = stored
            else:
                if info is None:
                    raise DatasetError(f"{self.root} is not a dataset yet: DatasetInfo is required")
                write_atomic(meta_path, (json.dumps(info.to_json(), indent=2) + "\n").encode())
                fsync_dir(self.root)
                self.info = info
            self._manifest = self.root / "manifest.jsonl"
            self._manifest.touch(exist_ok=True)
            self._repair_torn_tail()
        except OSError as err:
            raise DatasetError(f"cannot open dataset {self.root} for writing: {err}") from err
        self.records: list[SampleRecord] = read_manifest(self._manifest)
        self._ids = {r.sample_id for r in self.records}

    def __len__(self) -> int:
        return len(self.records)

    def __contains__(self, sample_id: str) -> bool:
        return sample_id in self._ids

    def _repair_torn_tail(self) -> None:
        data = read_regular_file(self._manifest, MAX_MANIFEST_BYTES, "manifest")
        if data and not data.endswith(b"\n"):
            keep = data.rfind(b"\n") + 1
            with open(self._manifest, "r+b") as f:
                f.truncate(keep)
                os.fsync(f.fileno())

    def encode(
        self,
        *,
        sample_id: str,
        object_name: str,
        grasp_id: int,
        finger: str,
        grasp_pose: Sequence[float],
        tactile_rgb: np.ndarray,
        tactile_diff_rgb: np.ndarray,
        depth_map_m: np.ndarray,
        registration_fitness: float,
        stamps_ns: dict[str, int] | None = None,
        model_to_gel: np.ndarray | None = None,
        gel_to_world: np.ndarray | None = None,
        model_to_world: np.ndarray | None = None,
    ) -> EncodedSample:
        """Check one sample and encode its files, touching nothing on disk: ``write_together``
        then lands it (with its grasp's other finger). DatasetError for bad arrays or fields."""
        if not isinstance(sample_id, str) or not SAMPLE_ID.match(sample_id):
            raise DatasetError(
                f"sample id {sample_id!r} must be 1-128 characters of [A-Za-z0-9_.-], not starting with '.', '_' or '-'"
            )
        if finger not in FINGERS:
            raise DatasetError(f"sample {sample_id}: finger must be one of {FINGERS}, got {finger!r}")
        pose = tuple(float(v) for v in grasp_pose)
        if len(pose) != 4 or not all(np.isfinite(pose)):
            raise DatasetError(
                f"sample {sample_id}: grasp_pose must be 4 finite numbers "
                f"(x, y, z [m], theta_z [rad]), got {grasp_pose}"
            )
        if not np.isfinite(registration_fitness):
            raise DatasetError(f"sample {sample_id}: registration_fitness must be finite, got {registration_fitness}")
        check_sample_arrays(self.info, tactile_rgb, tactile_diff_rgb, depth_map_m, sample_id)
        poses = _checked_poses(
            sample_id, model_to_gel=model_to_gel, gel_to_world=gel_to_world, model_to_world=model_to_world
        )

        payloads = {
            "tactile": encode_png(np.asarray(tactile_rgb)),
            "tactile_diff": encode_png(np.asarray(tactile_diff_rgb)),
            "depth": encode_npy(np.asarray(depth_map_m)),
        }
        files = sample_files(sample_id)
        record = SampleRecord(
            sample_id=sample_id,
            object_name=str(object_name),
            grasp_id=int(grasp_id),
            finger=finger,
            grasp_pose=pose,
            stamps_ns={str(k): int(v) for k, v in (stamps_ns or {}).items()},  # type: ignore[arg-type]
            registration_fitness=float(registration_fitness),
            files=files,
            sha256={kind: sha256_hex(data) for kind, data in payloads.items()},
            **poses,
        )
        return EncodedSample(record, payloads)

    def write(self, **fields: Any) -> SampleRecord:
        """Write one sample (``fields`` as for ``encode``) atomically and return its record."""
        return self.write_together([self.encode(**fields)])[0]

    def write_together(self, samples: Sequence[EncodedSample]) -> list[SampleRecord]:
        """Land several samples (a grasp's two fingers) together: all of them, or none.

        Every file of every sample is written first; their manifest lines follow in one
        append, so a crash or a full disk at any point leaves either all the samples or none
        (their files, orphaned, are overwritten on resume). Raises DatasetError for a repeated
        sample id and for a disk error; the dataset is left as it was.
        """
        ids = [s.record.sample_id for s in samples]
        repeated = sorted({i for i in ids if i in self._ids or ids.count(i) > 1})
        if repeated:
            raise DatasetError(f"sample(s) {repeated} already in {self.root} or given twice: refusing a duplicate")
        lines = b"".join((json.dumps(s.record.to_json(), allow_nan=False) + "\n").encode() for s in samples)
        try:
            for sample in samples:
                for kind, data in sample.payloads.items():
                    write_atomic(self.root / sample.record.files[kind], data)
            for kind in FILE_KINDS:
                fsync_dir(self.root / kind)
            self._append_manifest(lines)
        except OSError as err:
            raise DatasetError(
                f"could not write sample {' and '.join(ids)} to {self.root}: {err} "
                "(the dataset is intact; free space or fix permissions and resume)"
            ) from err
        self.records += [s.record for s in samples]
        self._ids.update(ids)
        return [s.record for s in samples]

    def drop_incomplete_grasps(self) -> list[str]:
        """Remove from the manifest every sample whose grasp lacks one of the fingers, and
        return their ids: a resuming collector then redoes those grasps whole, so no grasp
        pairs a finger of one attempt with a finger of another. Their files stay, to be
        overwritten by the redo."""
        fingers: dict[str, set[str]] = {}
        for record in self.records:
            fingers.setdefault(record.grasp_key, set()).add(record.finger)
        lone = [r for r in self.records if fingers[r.grasp_key] != set(FINGERS)]
        if not lone:
            return []
        keep = [r for r in self.records if fingers[r.grasp_key] == set(FINGERS)]
        text = "".join(json.dumps(r.to_json(), allow_nan=False) + "\n" for r in keep).encode()
        try:
            write_atomic(self._manifest, text)
            fsync_dir(self.root)
        except OSError as err:
            raise DatasetError(f"could not rewrite the manifest of {self.root}: {err} (it is intact)") from err
        self.records = keep
        self._ids = {r.sample_id for r in keep}
        return [r.sample_id for r in lone]

    def _append_manifest(self, lines: bytes) -> None:
        with open(self._manifest, "ab") as f:
            size = f.tell()
            try:
                f.write(lines)
                f.flush()
                os.fsync(f.fileno())
            except OSError:
                # A partial append would corrupt the manifest or split a grasp: cut it all back.
                f.truncate(size)
                raise


def _checked_poses(sample_id: str, **poses: np.ndarray | None) -> dict[str, tuple[tuple[float, ...], ...] | None]:
    """Each named 4x4 pose as a record holds it (None stays None); DatasetError naming the sample."""
    try:
        return {name: None if pose is None else rigid_transform_tuple(pose, name) for name, pose in poses.items()}
    except DatasetError as err:
        raise DatasetError(f"sample {sample_id}: {err}") from err
