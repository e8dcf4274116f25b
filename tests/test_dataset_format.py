"""The on-disk dataset: atomic writes, resume, failures, checks, splits, export."""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import signal
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dataset import files as dataset_files
from dataset import writer as dataset_writer
from dataset.check import check_dataset, content_checksum
from dataset.cli import add_commands
from dataset.export import export_pix2pix
from dataset.images import resize_rgb, subtract_background
from dataset.reader import DatasetReader
from dataset.records import (
    FILE_KINDS,
    FINGERS,
    DatasetError,
    DatasetInfo,
    EncodedSample,
    SampleRecord,
    rigid_transform_tuple,
)
from dataset.splits import leave_one_object_out, split_grasps, split_records
from dataset.synth import SHAPES, depth_map_from_surface, random_surface, write_synthetic_dataset
from dataset.writer import DatasetWriter

INFO = DatasetInfo(
    image_height=100,
    image_width=100,
    depth_range_m=(-0.0015, 0.0025),
    scene="test",
    effects=("none",),
    code_version="test",
    split_seed=3,
)


class ShadingRenderer:
    """Stand-in for the simulated GelSight: colour follows the indentation's slope and depth."""

    def render(self, gel_gap_mm: np.ndarray) -> np.ndarray:
        depth = np.clip(-np.nan_to_num(gel_gap_mm, posinf=1.0), 0.0, 1.5)
        grad_z, grad_x = np.gradient(depth)
        rgb = np.stack([128 + 400 * grad_x, 128 + 400 * grad_z, 90 + 100 * depth], axis=-1)
        return np.clip(rgb, 0, 255).astype(np.uint8)


def sample_arrays(seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    image = rng.integers(0, 256, (100, 100, 3), dtype=np.uint8)
    depth = rng.uniform(-0.001, 0.002, (100, 100)).astype(np.float32)
    depth[:5] = np.nan
    return {
        "tactile_rgb": image,
        "tactile_diff_rgb": subtract_background(image, np.full_like(image, 100)),
        "depth_map_m": depth,
    }


def write_sample(
    writer: DatasetWriter,
    grasp: int,
    finger: str,
    obj: str = "mug",
    pose: tuple[float, float, float, float] = (0.1, 0.2, 0.05, 0.3),
    stamps_ns: dict[str, int] | None = None,
) -> SampleRecord:
    return writer.write(
        sample_id=f"{obj}-g{grasp:03d}-{finger}",
        object_name=obj,
        grasp_id=grasp,
        finger=finger,
        grasp_pose=pose,
        registration_fitness=0.9,
        stamps_ns=stamps_ns or {"tactile": 1, "depth": 2},
        **sample_arrays(grasp * 2 + (finger == "right")),
    )


def test_round_trip_preserves_arrays_and_manifest(tmp_path: Path) -> None:
    writer = DatasetWriter(tmp_path, INFO)
    record = write_sample(writer, 1, "left")
    reader = DatasetReader(tmp_path)
    assert reader.info == INFO and reader.records == [record]
    sample = reader.load(record.sample_id)
    expected = sample_arrays(2)
    np.testing.assert_array_equal(sample.tactile_rgb, expected["tactile_rgb"])
    np.testing.assert_array_equal(sample.tactile_diff_rgb, expected["tactile_diff_rgb"])
    np.testing.assert_array_equal(sample.depth_map_m, expected["depth_map_m"])  # NaN == NaN here
    line = json.loads((tmp_path / "manifest.jsonl").read_text().splitlines()[0])
    assert line["grasp_pose"] == [0.1, 0.2, 0.05, 0.3] and set(line["sha256"]) == set(FILE_KINDS)
    assert cv2.imread(str(tmp_path / record.files["tactile"])).shape == (100, 100, 3)


def test_resume_continues_and_refuses_duplicates(tmp_path: Path) -> None:
    write_sample(DatasetWriter(tmp_path, INFO), 1, "left")
    writer = DatasetWriter(tmp_path)  # reopened: info comes from dataset.json
    assert len(writer) == 1 and "mug-g001-left" in writer
    with pytest.raises(DatasetError, match="duplicate"):
        write_sample(writer, 1, "left")
    write_sample(writer, 1, "right")
    assert [r.sample_id for r in DatasetReader(tmp_path).records] == ["mug-g001-left", "mug-g001-right"]
    with pytest.raises(DatasetError, match="dataset.json holds another dataset") as refused:
        DatasetWriter(tmp_path, dataclasses.replace(INFO, depth_range_m=(-0.01, 0.01), code_version="dtx 9.9"))
    # Only what differs is named, as it is there and as it is now, and what to do.
    message = str(refused.value)
    assert (
        "depth_range_m" in message
        and "code_version 'test' there, 'dtx 9.9' now" in message
        and "remove the directory" in message
    )
    assert "image_height" not in message
    assert len(DatasetReader(tmp_path).records) == 2  # nothing written is lost


def test_torn_manifest_tail_is_refused_by_reader_and_repaired_by_writer(tmp_path: Path) -> None:
    write_sample(DatasetWriter(tmp_path, INFO), 1, "left")
    with open(tmp_path / "manifest.jsonl", "a") as f:
        f.write('{"sample_id": "mug-g001-ri')
    with pytest.raises(DatasetError, match="incomplete"):
        DatasetReader(tmp_path)
    writer = DatasetWriter(tmp_path)
    write_sample(writer, 1, "right")
    assert len(DatasetReader(tmp_path)) == 2


def test_corrupt_manifest_line_and_checksum_mismatch_are_reported(tmp_path: Path) -> None:
    writer = DatasetWriter(tmp_path, INFO)
    record = write_sample(writer, 1, "left")
    write_sample(writer, 1, "right")
    depth_file = tmp_path / record.files["depth"]
    data = bytearray(depth_file.read_bytes())
    data[-1] ^= 0xFF
    depth_file.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match="checksum mismatch"):
        DatasetReader(tmp_path).load(record.sample_id)
    report = check_dataset(tmp_path)
    assert not report.ok and any("checksum" in p for p in report.problems)

    manifest = tmp_path / "manifest.jsonl"
    lines = manifest.read_text().splitlines()
    manifest.write_text("not json\n" + lines[1] + "\n")
    with pytest.raises(DatasetError, match=r"manifest.jsonl:1: corrupt"):
        DatasetReader(tmp_path)


def test_missing_file_fails_the_check(tmp_path: Path) -> None:
    writer = DatasetWriter(tmp_path, INFO)
    record = write_sample(writer, 1, "left")
    (tmp_path / record.files["tactile"]).unlink()
    report = check_dataset(tmp_path)
    assert not report.ok and "cannot read" in report.problems[0]


@pytest.mark.parametrize(
    "change, message",
    [
        ({"tactile_rgb": np.zeros((100, 100, 3), np.float32)}, "uint8"),
        ({"tactile_rgb": np.zeros((64, 100, 3), np.uint8)}, "dataset images are"),
        ({"depth_map_m": np.zeros((100, 100), np.float64)}, "float32"),
        ({"depth_map_m": np.full((100, 100), -np.inf, np.float32)}, "-inf"),
        ({"finger": "thumb"}, "finger"),
        ({"grasp_pose": (0.0, 0.0, np.nan, 0.0)}, "grasp_pose"),
        ({"registration_fitness": float("nan")}, "registration_fitness"),
        ({"sample_id": "../escape"}, "sample id"),
    ],
)
def test_bad_samples_are_refused_with_a_clear_error(tmp_path: Path, change: dict, message: str) -> None:
    writer = DatasetWriter(tmp_path, INFO)
    kwargs = dict(
        sample_id="s-1",
        object_name="mug",
        grasp_id=1,
        finger="left",
        grasp_pose=(0, 0, 0, 0),
        registration_fitness=1.0,
        **sample_arrays(0),
    )
    kwargs.update(change)
    with pytest.raises(DatasetError, match=message):
        writer.write(**kwargs)
    assert len(DatasetReader(tmp_path)) == 0


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores directory permissions")
def test_read_only_directory_gives_clear_error_and_intact_dataset(tmp_path: Path) -> None:
    writer = DatasetWriter(tmp_path, INFO)
    write_sample(writer, 1, "left")
    for sub in ("tactile", "tactile_diff", "depth"):
        (tmp_path / sub).chmod(0o555)
    try:
        with pytest.raises(DatasetError, match="could not write sample mug-g001-right"):
            write_sample(writer, 1, "right")
    finally:
        for sub in ("tactile", "tactile_diff", "depth"):
            (tmp_path / sub).chmod(0o755)
    assert check_dataset(tmp_path).ok and len(DatasetReader(tmp_path)) == 1


def test_permission_denied_is_a_clear_error_even_as_root(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Root ignores chmod, so the refusal of an unwritable directory is simulated here."""
    writer = DatasetWriter(tmp_path, INFO)
    write_sample(writer, 1, "left")

    def refuse(path: object, mode: str = "r", *args: object, **kwargs: object) -> object:
        if any(c in mode for c in "wa+"):
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return open(path, mode, *args, **kwargs)

    # Every write of the dataset: the files (written atomically) and the manifest (appended).
    monkeypatch.setattr(dataset_files, "open", refuse, raising=False)
    monkeypatch.setattr(dataset_writer, "open", refuse, raising=False)
    with pytest.raises(DatasetError, match="Permission denied"):
        write_sample(writer, 1, "right")
    monkeypatch.undo()
    assert check_dataset(tmp_path).ok and len(DatasetReader(tmp_path)) == 1
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    with pytest.raises(DatasetError, match="cannot open dataset"):
        DatasetWriter(blocker / "ds", INFO)


@pytest.mark.parametrize("failing_call", [1, 3, 4])
def test_full_disk_leaves_dataset_intact_and_resumable(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failing_call: int
) -> None:
    """ENOSPC at the first file, the third file, or the manifest append (4th fsync of files)."""
    writer = DatasetWriter(tmp_path, INFO)
    write_sample(writer, 1, "left")
    real_fsync, calls = os.fsync, {"n": 0}

    def fsync(fd: int) -> None:
        if not os.path.isdir(f"/proc/self/fd/{fd}"):
            calls["n"] += 1
            if calls["n"] == failing_call:
                raise OSError(errno.ENOSPC, "No space left on device")
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    with pytest.raises(DatasetError, match="No space left"):
        write_sample(writer, 1, "right")
    monkeypatch.setattr(os, "fsync", real_fsync)
    assert check_dataset(tmp_path).ok and len(DatasetReader(tmp_path)) == 1
    assert not list(tmp_path.rglob(".*.tmp"))
    write_sample(DatasetWriter(tmp_path), 1, "right")
    assert check_dataset(tmp_path).ok and len(DatasetReader(tmp_path)) == 2


def test_missing_dataset_and_bad_info_are_clear(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="does not exist"):
        DatasetReader(tmp_path / "nope")
    with pytest.raises(DatasetError, match="DatasetInfo is required"):
        DatasetWriter(tmp_path / "new")
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "dataset.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(DatasetError, match="format is 'other'"):
        DatasetReader(tmp_path / "bad")


@settings(max_examples=30, deadline=None)
@given(n=st.integers(1, 300), seed=st.integers(0, 2**31), shift=st.integers(0, 50))
def test_split_is_deterministic_order_free_and_proportional(n: int, seed: int, shift: int) -> None:
    keys = [f"obj/{i}" for i in range(n)]
    rotated = keys[shift % n :] + keys[: shift % n]
    a, b = split_grasps(keys, seed), split_grasps(rotated, seed)
    assert a == b
    counts = {name: sum(v == name for v in a.values()) for name in ("train", "val", "test")}
    assert abs(counts["train"] - 0.7 * n) <= 1.5 and abs(counts["test"] - 0.15 * n) <= 1.5
    if n >= 3:
        assert min(counts.values()) >= 1


def test_split_keeps_fingers_together_and_loo_holds_out_one_object(tmp_path: Path) -> None:
    writer = DatasetWriter(tmp_path, INFO)
    for grasp in range(10):
        for finger in ("left", "right"):
            write_sample(writer, grasp, finger, obj="mug" if grasp < 6 else "can")
    records = DatasetReader(tmp_path).records
    splits = split_records(records, seed=3)
    for name, members in splits.items():
        for record in members:
            partner = {"left": "right", "right": "left"}[record.finger]
            assert record.sample_id.replace(record.finger, partner) in {r.sample_id for r in members}
    assert split_records(records, seed=3) == splits and split_records(records, seed=4) != splits
    loo = leave_one_object_out(records, "can", seed=3)
    assert {r.object_name for r in loo["test"]} == {"can"} and len(loo["test"]) == 8
    assert {r.object_name for r in loo["train"] + loo["val"]} == {"mug"} and loo["val"]
    with pytest.raises(DatasetError, match="not in the dataset"):
        leave_one_object_out(records, "drill", seed=3)


def test_check_cli_and_pix2pix_export(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import argparse

    root = tmp_path / "ds"
    writer = DatasetWriter(root, INFO)
    for grasp in range(6):
        for finger in ("left", "right"):
            write_sample(writer, grasp, finger)
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers())
    args = parser.parse_args(["dataset", "check", str(root)])
    assert args.func(args) == 0 and "12 samples, 6 grasps" in capsys.readouterr().out

    counts = export_pix2pix(root, tmp_path / "ab")
    assert sum(counts.values()) == 12 and counts["test"] >= 1
    record = DatasetReader(root).records[0]
    split = next(name for name in counts if (tmp_path / "ab" / name / f"{record.sample_id}.png").exists())
    pair = cv2.cvtColor(cv2.imread(str(tmp_path / "ab" / split / f"{record.sample_id}.png")), cv2.COLOR_BGR2RGB)
    assert pair.shape == (100, 200, 3)
    np.testing.assert_array_equal(pair[:, 100:], DatasetReader(root).load(record).tactile_rgb)
    assert np.all(pair[:5, :100] == 255)  # NaN rows = empty bins = far = white

    (root / record.files["depth"]).write_bytes(b"garbage")
    args = parser.parse_args(["dataset", "check", str(root)])
    assert args.func(args) == 1


def test_synthetic_dataset_is_reproducible_and_resumable(tmp_path: Path) -> None:
    renderer = ShadingRenderer()
    write_synthetic_dataset(tmp_path / "a", 10, seed=5, renderer=renderer, pixel_pitch_mm=(0.15, 0.2))
    write_synthetic_dataset(tmp_path / "b", 4, seed=5, renderer=renderer, pixel_pitch_mm=(0.15, 0.2))
    write_synthetic_dataset(tmp_path / "b", 10, seed=5, renderer=renderer, pixel_pitch_mm=(0.15, 0.2))
    a, b = DatasetReader(tmp_path / "a"), DatasetReader(tmp_path / "b")
    assert [r.sha256 for r in a.records] == [r.sha256 for r in b.records] and len(a) == 10
    assert check_dataset(tmp_path / "a").ok


@pytest.mark.parametrize("shape", SHAPES)
def test_synthetic_surfaces_press_into_the_gel(shape: str) -> None:
    surface = random_surface(shape, np.random.default_rng(1))
    depth = depth_map_from_surface(surface, 100, crop_mm=24.0, y_far_m=0.0025)
    assert depth.dtype == np.float32 and depth.shape == (100, 100) and depth.max() <= 0.0025
    lowest = depth.min()
    assert -0.0011 < lowest < -0.00019  # pressed 0.2-1.0 mm, sampled on a grid


def test_check_finds_duplicate_lines_and_inconsistent_grasps(tmp_path: Path) -> None:
    writer = DatasetWriter(tmp_path, INFO)
    write_sample(writer, 1, "left")
    write_sample(writer, 1, "right")
    manifest = tmp_path / "manifest.jsonl"
    lines = manifest.read_text().splitlines()
    manifest.write_text("\n".join(lines + [lines[0]]) + "\n")
    report = check_dataset(tmp_path)
    assert not report.ok and "appears twice" in report.problems[0]

    right = json.loads(lines[1])
    right["grasp_pose"] = [0.0, 0.0, 0.0, 0.0]
    right["finger"] = "left"
    manifest.write_text(lines[0] + "\n" + json.dumps(right) + "\n")
    problems = check_dataset(tmp_path).problems
    assert any("more than once" in p for p in problems) and any("grasp pose" in p for p in problems)


def test_model_pose_and_crop_round_trip_and_bad_ones_are_refused(tmp_path: Path) -> None:
    """What a depth-map can be made again from: the crop in dataset.json, the model's pose in
    the gel frame per sample; both optional, so datasets without models still read."""
    info = DatasetInfo(**{**INFO.__dict__, "depth_crop_m": (0.0239, 0.015, 0.0189)})
    writer = DatasetWriter(tmp_path, info)
    pose = np.eye(4)
    pose[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    pose[:3, 3] = [0.01, -0.02, 0.123456789012345]
    arrays = sample_arrays(0)
    record = writer.write(
        sample_id="a",
        object_name="mug",
        grasp_id=0,
        finger="left",
        grasp_pose=(0, 0, 0, 0),
        registration_fitness=1.0,
        model_to_gel=pose,
        **arrays,
    )
    reader = DatasetReader(tmp_path)
    assert reader.info.depth_crop_m == (0.0239, 0.015, 0.0189)
    assert np.array_equal(np.array(reader.record("a").model_to_gel), pose) and reader.records == [record]
    skewed = pose.copy()
    skewed[0, 0] = 2.0
    for bad in (skewed, np.full((4, 4), np.nan), np.eye(3)):
        with pytest.raises(DatasetError, match="sample b: model_to_gel must be a finite 4x4 rigid transform"):
            writer.write(
                sample_id="b",
                object_name="mug",
                grasp_id=1,
                finger="left",
                grasp_pose=(0, 0, 0, 0),
                registration_fitness=1.0,
                model_to_gel=bad,
                **arrays,
            )
    assert len(DatasetReader(tmp_path)) == 1
    meta = json.loads((tmp_path / "dataset.json").read_text())
    (tmp_path / "dataset.json").write_text(json.dumps({**meta, "depth_crop_m": [0.02, -1.0, 0.02]}))
    with pytest.raises(DatasetError, match="depth_crop_m must be 3 positive extents"):
        DatasetReader(tmp_path)


@settings(max_examples=300, deadline=None)
@given(
    angles=st.tuples(*[st.floats(-np.pi, np.pi)] * 3),
    offset=st.tuples(*[st.floats(-1.0, 1.0)] * 3),
    where=st.tuples(st.integers(0, 3), st.integers(0, 3)),
    error_exponent=st.floats(-12.0, -3.0),
)
def test_a_rigid_transform_is_told_within_np_allclose_tolerances(
    angles: tuple[float, float, float],
    offset: tuple[float, float, float],
    where: tuple[int, int],
    error_exponent: float,
) -> None:
    """The reader's check of each pose, written out for speed, takes what ``np.allclose`` took
    (rtol 1e-5; atol 1e-8 on the last row, 1e-6 on R Rᵀ = I) and refuses the rest."""
    from scipy.spatial.transform import Rotation

    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_euler("xyz", angles).as_matrix()
    matrix[:3, 3] = offset
    matrix[where] += 10.0**error_exponent
    rigid = np.allclose(matrix[3], [0, 0, 0, 1]) and np.allclose(
        matrix[:3, :3] @ matrix[:3, :3].T, np.eye(3), atol=1e-6
    )
    if rigid:
        assert rigid_transform_tuple(matrix) == tuple(tuple(float(v) for v in row) for row in matrix)
    else:
        with pytest.raises(DatasetError, match="model_to_gel must be a finite 4x4 rigid transform"):
            rigid_transform_tuple(matrix)


def test_redepth_cli_says_what_is_wrong(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import argparse

    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers())
    root = tmp_path / "ds"
    write_sample(DatasetWriter(root, INFO), 0, "left")  # no crop, no model pose: not made from a model
    for argv, code, message in (
        ([], 2, "give --density"),
        (["--density", "1", "10", "--out", str(tmp_path / "x")], 2, "--out takes one density"),
        (["--density", "10", "--bins", "50"], 2, "--bins needs --out"),
        (["--density", "10"], 1, "records no depth-map crop"),
    ):
        args = parser.parse_args(["dataset", "redepth", str(root), *argv])
        assert args.func(args) == code
        assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "ds_density_10").exists()


def test_resize_rgb_averages_when_shrinking_and_keeps_a_right_sized_image() -> None:
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (4, 6, 3), dtype=np.uint8)
    assert resize_rgb(image, 4, 6) is image
    halved = resize_rgb(image, 2, 3)
    blocks = image.reshape(2, 2, 3, 2, 3).astype(np.float64).mean(axis=(1, 3))
    assert halved.shape == (2, 3, 3) and np.all(np.abs(halved - blocks) <= 0.5 + 1e-9)
    doubled = resize_rgb(image, 8, 12)
    assert doubled.shape == (8, 12, 3) and doubled.min() >= image.min() and doubled.max() <= image.max()


def encoded_grasp(writer: DatasetWriter, grasp: int, attempt: int) -> list[EncodedSample]:
    """Both fingers of one attempt at a grasp: the attempt sets the pose and the stamps."""
    return [
        writer.encode(
            sample_id=f"mug-g{grasp:03d}-{finger}",
            object_name="mug",
            grasp_id=grasp,
            finger=finger,
            grasp_pose=(0.1, 0.2, 0.05 + 0.001 * attempt, 0.3),
            registration_fitness=0.9,
            stamps_ns={"tactile": attempt},
            **sample_arrays(10 * attempt + (finger == "right")),
        )
        for finger in FINGERS
    ]


def resume_and_redo(root: Path, grasp: int) -> None:
    """What a resuming collector does: drop lone fingers, redo missing grasps whole (a fresh attempt)."""
    writer = DatasetWriter(root)
    writer.drop_incomplete_grasps()
    if f"mug-g{grasp:03d}-left" not in writer:
        writer.write_together(encoded_grasp(writer, grasp, attempt=2))


def assert_every_grasp_whole(root: Path, grasps: int) -> None:
    report = check_dataset(root)
    assert report.ok, report.problems
    records = DatasetReader(root).records
    assert sorted(r.sample_id for r in records) == sorted(f"mug-g{g:03d}-{f}" for g in range(grasps) for f in FINGERS)
    for g in range(grasps):
        pair = [r for r in records if r.grasp_id == g]
        assert pair[0].stamps_ns == pair[1].stamps_ns and pair[0].grasp_pose == pair[1].grasp_pose


# fsync and rename calls of a grasp's write: 6 files x (fsync, rename), 3 directories, the manifest.
_GRASP_WRITE_STEPS = 16


@pytest.mark.parametrize("kill_at", range(1, _GRASP_WRITE_STEPS + 2))
def test_a_kill_9_at_any_point_of_a_grasp_write_leaves_whole_grasps(tmp_path: Path, kill_at: int) -> None:
    """The collector's process is killed (SIGKILL, for real: a forked child) before its
    kill_at-th fsync or rename of a grasp's write (one past the last: after it); on resume
    every grasp has both fingers from one attempt and the check passes."""
    writer = DatasetWriter(tmp_path, INFO)
    writer.write_together(encoded_grasp(writer, 0, attempt=0))
    samples = encoded_grasp(writer, 1, attempt=1)
    pid = os.fork()
    if pid == 0:  # the child: writes grasp 1 and is killed part-way
        try:
            steps = {"n": 0}
            real_fsync, real_replace = os.fsync, os.replace

            def step(real):
                def call(*args):
                    steps["n"] += 1
                    if steps["n"] == kill_at:
                        os.kill(os.getpid(), signal.SIGKILL)
                    return real(*args)

                return call

            os.fsync, os.replace = step(real_fsync), step(real_replace)
            writer.write_together(samples)
            os.fsync, os.replace = real_fsync, real_replace
            if steps["n"] + 1 == kill_at:
                os.kill(os.getpid(), signal.SIGKILL)
        finally:
            os._exit(3)  # never reached when killed; 3 says the kill point was missed
    _, status = os.waitpid(pid, 0)
    assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL
    resume_and_redo(tmp_path, 1)
    assert_every_grasp_whole(tmp_path, 2)
    if kill_at <= _GRASP_WRITE_STEPS - 1:  # killed before the manifest's fsync: the redo wrote it
        assert DatasetReader(tmp_path).record("mug-g001-left").stamps_ns == {"tactile": 2}


@pytest.mark.parametrize("cut", ["inside the second line", "between the lines"])
def test_a_torn_grasp_append_loses_the_lone_finger_and_the_grasp_is_redone(tmp_path: Path, cut: str) -> None:
    writer = DatasetWriter(tmp_path, INFO)
    writer.write_together(encoded_grasp(writer, 0, attempt=0))
    writer.write_together(encoded_grasp(writer, 1, attempt=1))
    manifest = tmp_path / "manifest.jsonl"
    data = manifest.read_bytes()
    lines = data.splitlines(keepends=True)
    keep = len(b"".join(lines[:3])) + (10 if cut == "inside the second line" else 0)
    manifest.write_bytes(data[:keep])
    reopened = DatasetWriter(tmp_path)
    assert reopened.drop_incomplete_grasps() == ["mug-g001-left"]
    assert len(DatasetReader(tmp_path)) == 2 and check_dataset(tmp_path).ok
    resume_and_redo(tmp_path, 1)
    assert_every_grasp_whole(tmp_path, 2)
    assert DatasetReader(tmp_path).record("mug-g001-right").stamps_ns == {"tactile": 2}


def test_samples_given_together_are_refused_together(tmp_path: Path) -> None:
    writer = DatasetWriter(tmp_path, INFO)
    left, right = encoded_grasp(writer, 0, attempt=0)
    writer.write_together([left])
    with pytest.raises(DatasetError, match="duplicate"):
        writer.write_together([right, left])
    with pytest.raises(DatasetError, match="duplicate"):
        writer.write_together([right, right])
    assert [r.sample_id for r in DatasetReader(tmp_path).records] == ["mug-g000-left"]


def write_grasps(
    root: Path,
    order: list[int],
    stamp: int = 1,
    info: DatasetInfo = INFO,
    pose: tuple[float, float, float, float] = (0.1, 0.2, 0.05, 0.3),
) -> None:
    writer = DatasetWriter(root, info)
    for grasp in order:
        for finger in ("left", "right"):
            write_sample(writer, grasp, finger, pose=pose, stamps_ns={"tactile": stamp + grasp})


def test_the_content_checksum_ignores_when_and_by_which_build_and_sees_everything_else(tmp_path: Path) -> None:
    write_grasps(tmp_path / "a", [0, 1, 2])
    reference = content_checksum(tmp_path / "a")
    assert len(reference) == 64
    # other capture times, another build, grasps written in another order (a resumed session)
    write_grasps(tmp_path / "b", [2, 0, 1], stamp=10**18, info=dataclasses.replace(INFO, code_version="other"))
    assert content_checksum(tmp_path / "b") == reference
    # what the dataset holds: a pose, a grasp more, the description
    write_grasps(tmp_path / "c", [0, 1, 2], pose=(0.1, 0.2, 0.05, 0.30001))
    write_grasps(tmp_path / "d", [0, 1, 2, 3])
    write_grasps(tmp_path / "e", [0, 1, 2], info=dataclasses.replace(INFO, split_seed=4))
    assert len({reference} | {content_checksum(tmp_path / n) for n in "cde"}) == 4
    # a file's bytes: it no longer matches its manifest entry, which is an error, not another sum
    record = DatasetReader(tmp_path / "a").records[0]
    (tmp_path / "a" / record.files["depth"]).write_bytes(b"garbage")
    with pytest.raises(DatasetError, match="checksum mismatch"):
        content_checksum(tmp_path / "a")


def test_checksum_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import argparse

    write_grasps(tmp_path / "ds", [0])
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers())
    args = parser.parse_args(["dataset", "checksum", str(tmp_path / "ds")])
    assert args.func(args) == 0
    assert capsys.readouterr().out == f"{content_checksum(tmp_path / 'ds')}  {tmp_path / 'ds'}\n"
    args = parser.parse_args(["dataset", "checksum", str(tmp_path / "missing")])
    assert args.func(args) == 1 and "does not exist" in capsys.readouterr().err
