"""One model from a lab's many sessions: ``dtx train SESSION [SESSION ...]``, ``dtx evaluate
CHECKPOINT SESSION [SESSION ...]`` and their joint, leak-free split (models.sessions,
dataset.splits.split_sessions)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from dataset.reader import DatasetReader
from dataset.splits import SPLITS, TWIN_DEG, TWIN_MM, split_sessions, twin_grasps
from dataset.synth import write_synthetic_dataset
from models.checkpoint import TrainConfig, load_checkpoint, save_atomic
from models.cli import add_commands
from models.data import load_pairs, select_records
from models.networks import GeneratorConfig
from models.sessions import load_training_data, open_sessions, session_records
from models.train import train

sys.path.insert(0, str(Path(__file__).parent))
from test_dataset_format import ShadingRenderer

TINY = TrainConfig(
    epochs=1, epochs_decay=0, batch_size=8, ndf=8, threads=1, max_steps=2, generator=GeneratorConfig(ngf=8)
)
CONFIG_YAML = "epochs: 1\nepochs_decay: 0\nbatch_size: 8\nndf: 8\nthreads: 1\nmax_steps: 2\ngenerator: {ngf: 8}\n"


def _edit_info(root: Path, **fields: object) -> None:
    info = json.loads((root / "dataset.json").read_text())
    (root / "dataset.json").write_text(json.dumps({**info, **fields}))


@pytest.fixture(scope="module")
def sessions(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """day1, day2: two days' sessions of other grasps; again: day1's grasps collected again
    (a copy with another split seed), every grasp a twin of one of day1's."""
    tmp = tmp_path_factory.mktemp("sessions")
    for name, seed in (("day1", 1), ("day2", 2)):
        write_synthetic_dataset(tmp / name, 24, seed=seed, renderer=ShadingRenderer(), pixel_pitch_mm=(0.15, 0.2))
    shutil.copytree(tmp / "day1", tmp / "again")
    _edit_info(tmp / "again", split_seed=7)
    return {name: tmp / name for name in ("day1", "day2", "again")}


def _cli(*argv: str) -> int:
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers())
    args = parser.parse_args(list(argv))
    return int(args.func(args))


def test_one_session_selects_exactly_the_pairs_it_did_before(sessions: dict[str, Path]) -> None:
    """The train/val/test ids of one session are pinned (as before multi-session training), and
    its training tensors are models.data.load_pairs of select_records, as train loaded them."""
    reader = DatasetReader(sessions["day1"])
    ids = {split: [r.sample_id for r in session_records(open_sessions(sessions["day1"]), split)[0]] for split in SPLITS}
    assert ids["val"] == ["edge-g00003-left", "edge-g00003-right", "box-g00004-left", "box-g00004-right"]
    assert ids["test"] == ["edge-g00000-left", "edge-g00000-right", "sphere-g00008-left", "sphere-g00008-right"]
    assert ids["train"] == [
        f"{name}-g{grasp:05d}-{finger}"
        for name, grasp in (("edge", 1), ("box", 2), ("ridges", 5), ("box", 6), ("box", 7))
        + (("cylinder", 9), ("sphere", 10), ("ridges", 11))
        for finger in ("left", "right")
    ]
    assert ids == {split: [r.sample_id for r in select_records(reader, split)] for split in SPLITS}
    train_pairs, _, meta = load_training_data(sessions["day1"], TINY, (), torch.device("cpu"))
    x_train, y_train = train_pairs.tensors()
    expected = load_pairs(reader, select_records(reader, "train"), TINY.generator)
    assert torch.equal(x_train, expected[0]) and torch.equal(y_train, expected[1])
    assert meta["dataset"] == str(sessions["day1"].resolve()) and len(meta["sessions"]) == 1


def test_two_sessions_train_on_the_union_of_their_train_splits(sessions: dict[str, Path], tmp_path: Path) -> None:
    day1, day2 = DatasetReader(sessions["day1"]), DatasetReader(sessions["day2"])
    assert not twin_grasps([day1.records, day2.records])  # other grasps: each keeps its own split
    train_pairs, _, meta = load_training_data([sessions["day1"], sessions["day2"]], TINY, (), torch.device("cpu"))
    x_train, y_train = train_pairs.tensors()
    parts = [load_pairs(r, select_records(r, "train"), TINY.generator) for r in (day1, day2)]
    assert torch.equal(x_train, torch.cat([p[0] for p in parts])) and torch.equal(
        y_train, torch.cat([p[1] for p in parts])
    )
    assert "dataset" not in meta and [s["name"] for s in meta["sessions"]] == ["day1", "day2"]
    chosen = session_records(open_sessions([sessions["day1"], sessions["day2"]]), "train")
    pairs = [
        (i, r.sample_id)
        for split in SPLITS
        for i, records in enumerate(session_records(open_sessions([sessions["day1"], sessions["day2"]]), split))
        for r in records
    ]
    assert len(pairs) == len(set(pairs)) == len(day1) + len(day2)  # every pair once, in one split
    assert sum(map(len, chosen)) == len(x_train)

    out = tmp_path / "run"
    assert (
        _cli("train", str(sessions["day1"]), str(sessions["day2"]), "--config", _config(tmp_path), "--out", str(out))
        == 0
    )
    state = load_checkpoint(out / "checkpoint.pt")
    assert [s["fingerprint"] for s in state["sessions"]] == [s["fingerprint"] for s in meta["sessions"]]
    assert "serves" in state and "uncertainty" in state  # fit_serving ran on the same sessions


def _config(tmp_path: Path) -> str:
    path = tmp_path / "tiny.yaml"
    path.write_text(CONFIG_YAML)
    return str(path)


def test_sessions_split_leak_free_across_twin_grasps(sessions: dict[str, Path]) -> None:
    day1, again = DatasetReader(sessions["day1"]), DatasetReader(sessions["again"])
    twins = twin_grasps([day1.records, again.records])
    assert {a[1] for a, _ in twins} == {r.grasp_key for r in day1.records}  # every grasp collected again
    alone = [select_records(r, s) for r in (day1, again) for s in SPLITS]
    side_alone = {(i // 3, r.grasp_key): SPLITS[i % 3] for i, records in enumerate(alone) for r in records}
    assert any(side_alone[(0, k)] != side_alone[(1, k)] for k in {r.grasp_key for r in day1.records})  # would leak
    for order in ((0, 1), (1, 0)):
        readers = [(day1, again)[i] for i in order]
        joint = split_sessions([r.records for r in readers], [r.info.split_seed for r in readers], order=["b", "a"])
        side = {}
        for i, splits in enumerate(joint):
            for name in SPLITS:
                for record in splits[name]:
                    assert side.setdefault((order[i], record.grasp_key), name) == name  # both fingers together
        assert all(side[(0, a[1])] == side[(1, b[1])] for a, b in twins)
    # In the sessions' split made from their fingerprints, the order they are given in changes nothing.
    forward = session_records(open_sessions([sessions["day1"], sessions["again"]]), "test")
    backward = session_records(open_sessions([sessions["again"], sessions["day1"]]), "test")
    assert forward == backward[::-1]


def test_twins_are_the_same_object_with_the_gel_within_the_tolerance(sessions: dict[str, Path]) -> None:
    record = DatasetReader(sessions["day1"]).records[0]
    pose = np.eye(4)

    def at(offset_mm: float, turn_deg: float, name: str = record.object_name) -> object:
        c, s = np.cos(np.radians(turn_deg)), np.sin(np.radians(turn_deg))
        moved = pose.copy()
        moved[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
        moved[0, 3] = offset_mm / 1e3
        return dataclasses.replace(record, object_name=name, model_to_gel=tuple(map(tuple, moved.tolist())))

    base = at(0.0, 0.0)
    assert twin_grasps([[base], [at(0.8 * TWIN_MM, 0.8 * TWIN_DEG)]])
    assert not twin_grasps([[base], [at(1.5 * TWIN_MM, 0.0)]])
    assert not twin_grasps([[base], [at(0.0, 1.5 * TWIN_DEG)]])
    assert not twin_grasps([[base], [at(0.0, 0.0, "another")]])


@pytest.mark.parametrize(
    ("field", "value", "says"),
    [
        ("depth_range_m", [-0.002, 0.003], "depth range"),
        ("image_height", 64, "image size"),
        ("depth_map_method", "surface", "depth-map method"),
        ("scene", "", "records no scene"),
    ],
)
def test_sessions_that_cannot_be_mixed_are_refused_with_nothing_written(
    sessions: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str], field: str, value: object, says: str
) -> None:
    other = tmp_path / "other"
    shutil.copytree(sessions["day2"], other)
    _edit_info(other, **{field: value})
    out = tmp_path / "run"
    assert _cli("train", str(sessions["day1"]), str(other), "--config", _config(tmp_path), "--out", str(out)) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and says in err and err.count("\n") == 1
    assert not out.exists()


@pytest.mark.parametrize(
    ("sigmas", "says"),
    [
        (["0.1", "0.2", "0.3"], "one value or one a session (2), got 3"),
        (["0.1", "nan"], "session_pose_sigmas_mm must be a finite number"),
        (["0.1", "0.2"], "session_pose_sigmas_mm needs a generator with a physics prior"),
    ],
)
def test_pose_uncertainties_that_do_not_fit_the_sessions_are_refused_with_nothing_written(
    sessions: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str], sigmas: list[str], says: str
) -> None:
    out = tmp_path / "run"
    day1, day2 = str(sessions["day1"]), str(sessions["day2"])
    argv = ["train", day1, day2, "--config", _config(tmp_path), "--out", str(out), "--session-pose-sigma-mm", *sigmas]
    assert _cli(*argv) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and says in err
    assert not out.exists()


@pytest.fixture(scope="module")
def two_day_checkpoint(sessions: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    config = dataclasses.replace(TINY, hold_out_object="box")
    return train([sessions["day1"], sessions["day2"]], config, tmp_path_factory.mktemp("two") / "run", progress=False)


def test_hold_out_object_leaves_it_out_of_every_session(sessions: dict[str, Path], two_day_checkpoint: Path) -> None:
    opened = open_sessions([sessions["day1"], sessions["day2"]])
    for split in ("train", "val"):
        assert all(r.object_name != "box" for records in session_records(opened, split, "box") for r in records)
    test = session_records(opened, "test", "box")
    assert [len(t) for t in test] == [8, 6] and all(r.object_name == "box" for t in test for r in t)
    # An object one session lacks: that session trains and validates on all of its own.
    sphere = session_records(opened, "test", "sphere")
    assert len(sphere[0]) == 4 and sphere[1] == []
    assert load_checkpoint(two_day_checkpoint)["train_config"]["hold_out_object"] == "box"


def test_evaluate_reports_each_session_and_the_whole(
    sessions: dict[str, Path], two_day_checkpoint: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    days = [str(sessions["day1"]), str(sessions["day2"])]
    assert _cli("evaluate", str(two_day_checkpoint), *days, "--hold-out-object", "box", "--json") == 0
    result = json.loads(capsys.readouterr().out)
    assert set(result["sessions"]) == {"day1", "day2"}
    assert [result["sessions"][d]["n"] for d in ("day1", "day2")] == [8, 6] and result["n"] == 14
    assert all("ssim_model_mean" in row for row in result["sessions"].values())
    assert result["sample_ids"][0].startswith("day1/")
    assert _cli("evaluate", str(two_day_checkpoint), *days, "--hold-out-object", "box") == 0
    text = capsys.readouterr().out
    assert "samples evaluated: 14" in text and "per session" in text and "day1" in text and "day2" in text


def test_an_old_single_dataset_checkpoint_still_serves_and_evaluates(
    sessions: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from models.serving import fit_serving

    path = train(sessions["day1"], TINY, tmp_path / "run", progress=False)
    state = load_checkpoint(path)
    del state["sessions"]  # as written before sessions were recorded: a single ``dataset``
    save_atomic(state, path)
    assert fit_serving(path, log=lambda line: None)["serves"] == "network"
    assert _cli("evaluate", str(path), str(sessions["day1"]), "--json") == 0
    assert json.loads(capsys.readouterr().out)["n"] == 4 and "sessions" not in load_checkpoint(path)


def test_a_prior_model_mixes_scenes_of_one_gelsight_and_refuses_another(
    sessions: dict[str, Path], tmp_path: Path
) -> None:
    """A checkpoint stores and serves one physics prior: sessions whose scenes hold other objects
    with the same GelSight share it; another GelSight, or a scene nothing can read, cannot."""
    from dataset.contact_library import write_contact_library
    from models.errors import ModelConfigError

    config = dataclasses.replace(TINY, generator=GeneratorConfig(ngf=8, prior=True, background=False))
    with pytest.raises(ModelConfigError, match="does not record its scene and depth crop"):
        load_training_data([sessions["day1"], sessions["day2"]], config, (), torch.device("cpu"))
    scenes = Path(__file__).resolve().parent.parent / "scenes"
    other = tmp_path / "other_gelsight.yaml"
    other.write_text(
        (scenes / "ycb_three.yaml").read_text().replace("elastomer_thickness_mm: 2.0", "elastomer_thickness_mm: 2.5")
    )
    roots = {
        name: write_contact_library(tmp_path / name, 8, seed=i, scene=str(scene)).root
        for i, (name, scene) in enumerate(
            (("three", scenes / "ycb_three.yaml"), ("unseen", scenes / "ycb_unseen.yaml"), ("other", other))
        )
    }
    train_pairs, _, meta = load_training_data([roots["three"], roots["unseen"]], config, (), torch.device("cpu"))
    assert len(train_pairs) > 0 and meta["prior"]["scene"].endswith("ycb_three.yaml")
    with pytest.raises(ModelConfigError, match="another GelSight or depth crop.*one physics prior.*prior: false"):
        load_training_data([roots["three"], roots["other"]], config, (), torch.device("cpu"))
    # Without a prior nothing a GelSight draws is served: its sessions mix, each pair its own sensor's.
    session_only = dataclasses.replace(config, generator=GeneratorConfig(ngf=8, prior=False, background=False))
    train_pairs, _, meta = load_training_data([roots["three"], roots["other"]], session_only, (), torch.device("cpu"))
    assert len(train_pairs) > 0 and meta.get("prior") is None
