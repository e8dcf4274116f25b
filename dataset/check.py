"""Verify a dataset directory sample by sample (``dtx dataset check``)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from dataset.reader import DatasetReader
from dataset.records import FILE_KINDS, FINGERS, DatasetError, SampleRecord
from dataset.splits import SPLITS, split_records


@dataclasses.dataclass
class CheckReport:
    """What a check found; the dataset is sound when ``problems`` is empty."""

    root: Path
    problems: list[str]
    samples: int = 0
    grasps: int = 0
    objects: dict[str, int] = dataclasses.field(default_factory=dict)
    split_samples: dict[str, int] = dataclasses.field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.problems

    def summary(self) -> str:
        lines = [f"dataset {self.root}: {self.samples} samples, {self.grasps} grasps"]
        lines += [f"  object {name}: {count} samples" for name, count in sorted(self.objects.items())]
        lines.append("  split " + ", ".join(f"{k} {v}" for k, v in self.split_samples.items()))
        lines.append("OK" if self.ok else f"{len(self.problems)} problem(s):")
        lines += [f"  - {p}" for p in self.problems]
        return "\n".join(lines)


def _grasp_problems(records: list[SampleRecord]) -> list[str]:
    """Both finger samples of a grasp must agree on the grasp and name distinct fingers."""
    problems = []
    by_grasp: dict[str, list[SampleRecord]] = defaultdict(list)
    for record in records:
        by_grasp[record.grasp_key].append(record)
    for key, group in by_grasp.items():
        fingers = Counter(r.finger for r in group)
        repeated = [f for f, n in fingers.items() if n > 1]
        if repeated:
            problems.append(f"grasp {key}: finger(s) {repeated} recorded more than once")
        if len({r.grasp_pose for r in group}) > 1:
            problems.append(f"grasp {key}: its samples disagree on the grasp pose")
        if any(r.finger not in FINGERS for r in group):
            problems.append(f"grasp {key}: finger not in {FINGERS}")
    return problems


def check_dataset(root: str | os.PathLike[str]) -> CheckReport:
    """Check format, every file's presence, checksum and shape, duplicates and the split
    (the fingers of a grasp agree with each other, so the grasp is one split unit; no split
    is empty)."""
    report = CheckReport(root=Path(root), problems=[])
    try:
        reader = DatasetReader(root)
    except DatasetError as err:
        report.problems.append(str(err))
        return report
    records = reader.records
    report.samples = len(records)
    report.grasps = len({r.grasp_key for r in records})
    report.objects = dict(Counter(r.object_name for r in records))
    if not records:
        report.problems.append("the dataset has no samples")
        return report

    paths = Counter(r.files[kind] for r in records for kind in FILE_KINDS)
    report.problems += [f"file {p} is claimed by {n} samples" for p, n in paths.items() if n > 1]
    for record in records:
        try:
            sample = reader.load(record, verify=True)
        except DatasetError as err:
            report.problems.append(str(err))
            continue
        depth = sample.depth_map_m
        if np.all(~np.isfinite(depth)):
            report.problems.append(f"sample {record.sample_id}: depth-map has no occupied bin")
    report.problems += _grasp_problems(records)

    splits = split_records(records, reader.info.split_seed)
    report.split_samples = {name: len(splits[name]) for name in SPLITS}
    if report.grasps >= 3 and not all(report.split_samples.values()):
        report.problems.append(f"a split is empty: {report.split_samples}")
    return report


def content_checksum(root: str | os.PathLike[str]) -> str:
    """SHA-256 (hex) of what a dataset holds: its ``dataset.json`` and every sample's record,
    whose file hashes are verified against the files, in sample-id order. Left out: when each
    sample was captured and written (``stamps_ns``) and which build wrote it (``code_version``),
    so two sessions with the same seed, or a session and its resumed twin, give the same sum.
    A file that does not match its manifest entry raises DatasetError."""
    reader = DatasetReader(root)
    for record in reader.records:
        reader.load(record, verify=True)
    return records_checksum(reader)


def records_checksum(reader: DatasetReader) -> str:
    """:func:`content_checksum` read from the records alone, their files' hashes trusted: what
    names a session cheaply (a calibration's record of the session it placed the objects of)."""
    info = reader.info.to_json()
    del info["code_version"]
    samples = sorted((record.to_json() for record in reader.records), key=lambda row: row["sample_id"])
    for row in samples:
        del row["stamps_ns"]
    content = json.dumps({"dataset": info, "samples": samples}, sort_keys=True, allow_nan=False)
    return hashlib.sha256(content.encode()).hexdigest()
