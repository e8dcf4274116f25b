"""``dtx dataset export --format hf``: the Hub's layout, read back by ``datasets.load_dataset``
(offline, from the directory), every array equal to the session's files; the splits the
project's; refusals that write nothing; an existing directory replaced only whole."""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dataset.cli import add_commands
from dataset.reader import DatasetReader
from dataset.records import DatasetInfo
from dataset.splits import split_sessions
from dataset.writer import DatasetWriter


@pytest.fixture(autouse=True)
def offline(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Nothing from the Hub, and no cache outside the test's directory."""
    import datasets.config
    import huggingface_hub.constants

    for name in ("HF_HUB_OFFLINE", "HF_DATASETS_OFFLINE"):
        monkeypatch.setenv(name, "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf_home"))
    monkeypatch.setattr(datasets.config, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(datasets.config, "HF_DATASETS_OFFLINE", True)
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)


def _dtx(*argv: str) -> int:
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers())
    args = parser.parse_args(["dataset", *argv])
    return args.func(args)


def _rigid(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    matrix = np.eye(4)
    matrix[:3, :3] = q * np.sign(np.linalg.det(q))
    matrix[:3, 3] = rng.uniform(-0.3, 0.3, 3)
    return matrix


def _posed_session(root: Path, size: tuple[int, int] = (100, 100), grasps: int = 8) -> Path:
    """Pairs with every pose recorded (one sample without), NaN and +inf bins, a non-square size."""
    info = DatasetInfo(image_height=size[0], image_width=size[1], depth_range_m=(-0.0015, 0.0025), split_seed=4)
    writer = DatasetWriter(root, info)
    rng = np.random.default_rng(7)
    for grasp in range(grasps):
        for finger in ("left", "right"):
            image = rng.integers(0, 256, (*size, 3), dtype=np.uint8)
            depth = rng.uniform(-0.001, 0.002, size).astype(np.float32)
            depth[:3], depth[-2:, :5] = np.nan, np.inf
            poses = {} if grasp == 0 else {k: _rigid(rng) for k in ("model_to_gel", "gel_to_world", "model_to_world")}
            writer.write(
                sample_id=f"{'mug' if grasp % 2 else 'can'}-g{grasp:03d}-{finger}",
                object_name="mug" if grasp % 2 else "can",
                grasp_id=grasp,
                finger=finger,
                grasp_pose=(*rng.uniform(-0.2, 0.2, 3), rng.uniform(-3, 3)),
                registration_fitness=float(rng.uniform(0.5, 1.0)),
                tactile_rgb=image,
                tactile_diff_rgb=rng.integers(0, 256, (*size, 3), dtype=np.uint8),
                depth_map_m=depth,
                **poses,
            )
    return root


@pytest.fixture(scope="module")
def sessions(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("sessions")
    assert _dtx("synth", str(root / "synth"), "--samples", "24", "--seed", "1") == 0
    return {"synth": root / "synth", "posed": _posed_session(root / "posed")}


def _load(out: Path, cache: Path) -> Any:
    import datasets

    return datasets.load_dataset(str(out), cache_dir=str(cache))


def _pose(value: Any) -> Any:
    return None if value is None else [list(row) for row in value]


def _assert_row_equals_session(row: dict[str, Any], reader: DatasetReader) -> None:
    """Every array and field of ``row`` (default Python format) against the session's files."""
    record = reader.record(row["sample_id"])
    sample = reader.load(record)
    np.testing.assert_array_equal(np.asarray(row["tactile"].convert("RGB")), sample.tactile_rgb)
    np.testing.assert_array_equal(np.asarray(row["tactile_diff"].convert("RGB")), sample.tactile_diff_rgb)
    depth = np.asarray(row["depth_map_m"], dtype=np.float32)
    assert depth.shape == sample.depth_map_m.shape
    assert np.array_equal(depth.view(np.uint32), sample.depth_map_m.view(np.uint32))  # bit for bit, NaN too
    assert (row["object"], row["grasp_id"], row["finger"]) == (record.object_name, record.grasp_id, record.finger)
    assert row["grasp_pose_world"] == list(record.grasp_pose)
    assert row["registration_fitness"] == record.registration_fitness
    for name in ("gel_to_world", "model_to_world", "model_to_gel"):
        assert row[name] == _pose(getattr(record, name)), name


def test_two_sessions_round_trip_every_array_in_the_projects_splits(
    sessions: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "hf"
    assert _dtx("export", str(sessions["synth"]), str(sessions["posed"]), "--format", "hf", "--out", str(out)) == 0
    assert "read back with datasets.load_dataset" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["README.md", "data"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging left beside it
    loaded = _load(out, tmp_path / "cache")
    readers = {name: DatasetReader(path) for name, path in sessions.items()}
    expected = split_sessions(
        [r.records for r in readers.values()],
        [r.info.split_seed for r in readers.values()],
        "",
        [_fingerprint(r.root) for r in readers.values()],
    )
    for split, hf_split in (("train", "train"), ("val", "validation"), ("test", "test")):
        rows = loaded[hf_split]
        want = [(name, r.sample_id) for name, chosen in zip(readers, expected) for r in chosen[split]]
        assert list(zip(rows["session"], rows["sample_id"])) == want
        for row in rows:
            _assert_row_equals_session(row, readers[row["session"]])
    assert sum(loaded.num_rows.values()) == sum(len(r) for r in readers.values())
    numpy_row = loaded["train"].with_format("numpy")[0]
    assert numpy_row["depth_map_m"].dtype == np.float32 and numpy_row["tactile"].dtype == np.uint8
    card = (out / "README.md").read_text()
    assert card.startswith("---\nlicense: cc-by-4.0\n") and "data/validation-*" in card
    assert "`synth`" in card and "`posed`" in card and "metres" in card and "gel_left" in card


def _fingerprint(root: Path) -> str:
    from dataset.splits import session_fingerprint

    return session_fingerprint(root)


def test_one_session_in_shards_has_the_splits_training_selects(sessions: dict[str, Path], tmp_path: Path) -> None:
    from dataset.hf_export import export_hf
    from models.data import select_records

    out = tmp_path / "hf"
    counts = export_hf([sessions["posed"]], out, shard_bytes=5 * 100 * 100 * 10)  # 5 rows a shard
    shards = {p.name for p in (out / "data").iterdir()}
    assert shards == {
        f"{split}-{i:05d}-of-{-(-n // 5):05d}.parquet" for split, n in counts.items() for i in range(-(-n // 5))
    }
    assert max(counts.values()) > 5
    loaded = _load(out, tmp_path / "cache")
    reader = DatasetReader(sessions["posed"])
    for split, hf_split in (("train", "train"), ("val", "validation"), ("test", "test")):
        assert loaded[hf_split]["sample_id"] == [r.sample_id for r in select_records(reader, split)]
        assert set(loaded[hf_split]["session"]) == {"posed"}
    assert counts == loaded.num_rows


def test_sessions_of_another_size_are_refused_and_nothing_is_written(
    sessions: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    small = _posed_session(tmp_path / "small", size=(60, 80), grasps=2)
    out = tmp_path / "hf"
    assert _dtx("export", str(sessions["posed"]), str(small), "--format", "hf", "--out", str(out)) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "image_height" in err and str(small) in err
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_an_existing_out_is_refused_without_force_and_replaced_whole_with_it(
    sessions: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "hf"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    argv = ("export", str(sessions["synth"]), "--format", "hf", "--out", str(out))
    assert _dtx(*argv) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--force" in err
    assert [p.name for p in out.iterdir()] == ["keep.txt"] and (out / "keep.txt").read_text() == "mine"
    assert _dtx(*argv, "--force") == 0
    assert sorted(p.name for p in out.iterdir()) == ["README.md", "data"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    # Its own output (or any directory holding a session) is never what --force replaces.
    assert _dtx("export", str(sessions["synth"]), "--format", "hf", "--out", str(sessions["synth"]), "--force") == 1
    assert "overlaps" in capsys.readouterr().err and (sessions["synth"] / "dataset.json").exists()


def test_a_failure_mid_write_leaves_no_directory_and_the_old_one_whole(
    sessions: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    broken = tmp_path / "broken"
    shutil.copytree(sessions["synth"], broken)
    last = DatasetReader(broken).records[-1]
    (broken / last.files["depth"]).unlink()
    out = tmp_path / "hf"
    assert _dtx("export", str(broken), "--format", "hf", "--out", str(out)) == 1
    assert last.sample_id in capsys.readouterr().err and not out.exists()
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert _dtx("export", str(broken), "--format", "hf", "--out", str(out), "--force") == 1
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_not_a_dataset_and_pix2pix(
    sessions: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "empty").mkdir()
    assert _dtx("export", str(tmp_path / "empty"), "--format", "hf", "--out", str(tmp_path / "hf")) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is not a dataset" in err and not (tmp_path / "hf").exists()

    out = tmp_path / "ab"
    assert _dtx("export", str(sessions["synth"]), "--format", "pix2pix", "--out", str(out)) == 0
    record = DatasetReader(sessions["synth"]).records[0]
    assert len(list(out.glob(f"*/{record.sample_id}.png"))) == 1
    assert sum(1 for _ in out.glob("*/*.png")) == 24
    assert _dtx("export", str(sessions["synth"]), "--format", "pix2pix", "--out", str(out)) == 1
    assert "--force" in capsys.readouterr().err
    argv = (
        "export",
        str(sessions["synth"]),
        str(sessions["posed"]),
        "--format",
        "pix2pix",
        "--out",
        str(tmp_path / "x"),
    )
    assert _dtx(*argv) == 2 and "one session" in capsys.readouterr().err
