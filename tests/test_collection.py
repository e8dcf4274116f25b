"""The collection session end to end on the simulated scene: Algorithm 1 through every node,
crash safety under kill -9, a clear stop on an unwritable output, and replay from a bag."""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

import msgs
from benchmarks import fuzz
from benchmarks.collect import run_recorder_kills, run_session
from bus.bag import bag_info, iter_envelopes
from bus.registry import Registry
from dataset.announced import dataset_info, write_samples
from dataset.check import check_dataset, content_checksum
from dataset.images import deformation_map
from dataset.reader import DatasetReader
from dataset.records import DatasetError
from dataset.redepth import depth_maps_at_density, redepth_dataset, redepth_datasets
from dataset.synth import write_synthetic_dataset
from dataset.writer import DatasetWriter
from models.errors import ModelConfigError
from models.evaluate import CONTACT_LEVELS, evaluate, predict_dataset
from models.networks import GeneratorConfig, UNetGenerator
from msgs import strict_json
from nodes.collector import CollectorNode
from perception.depthmap import surface_bins
from perception.ssim import ssim_rgb
from report.ceiling import RUNGS, CeilingError, format_table, information_ceiling
from sim.cli import main as sim_cli
from sim.world import SimWorld
from workcell.kinematics import GRASP_FORCE_N, grasp_to_tcp_pose, pose_to_matrix

SMALL_BAG = Path(__file__).parent / "data" / "session_small.mcap"


def tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def collected(out: Path, grasps: int, seed: int) -> Path:
    """A clean session's dataset directory."""
    result = run_session(out, grasps=grasps, seed=seed, record=False)
    assert result["exit_code"] == 0, result.get("collector_log")
    strict_json.dumps(result)  # dtx bench collect --json prints it so: strict JSON, or ValueError
    return out


@pytest.fixture(scope="module")
def uninterrupted_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return collected(tmp_path_factory.mktemp("uninterrupted") / "session", grasps=6, seed=1)


@pytest.mark.slow
@pytest.mark.parametrize("node", ["collector", "gripper"])
def test_a_killed_node_is_respawned_and_the_dataset_is_exact(
    tmp_path: Path, node: str, uninterrupted_session: Path
) -> None:
    result = run_session(tmp_path / "session", grasps=6, seed=1, record=False, kill=node)
    assert result["exit_code"] == 0, result.get("collector_log")
    assert result["killed_pid"] is not None and result["respawned"]
    reader = DatasetReader(tmp_path / "session")
    ids = sorted(record.sample_id for record in reader.records)
    assert ids == sorted(f"g{g:05d}_{f}" for g in range(6) for f in ("left", "right"))
    assert check_dataset(tmp_path / "session").ok
    assert "dataset check OK" in result["collector_last_line"]
    # byte for byte the session nothing interrupted (what it redid, it redid exactly)
    assert content_checksum(tmp_path / "session") == content_checksum(uninterrupted_session)


@pytest.mark.slow
def test_a_recorder_killed_mid_session_leaves_no_empty_file_and_the_dataset_whole(tmp_path: Path) -> None:
    """The recorder of a collection session killed twice: each respawn writes a file of its own,
    every file holds messages up to near its kill, and the dataset does not notice. The kills
    fall in the session's first half, so that the last respawn has ~30 grasps of time to start
    on any machine (on a fast one, 30 grasps took 5 s and a kill at the 27th left too little)."""
    result = run_recorder_kills(tmp_path / "session", grasps=60, seed=0, kills=2, last_share=0.5)
    assert result["kills"] == 2 and result["exit_code"] == 0 and result["dataset_check_ok"], result
    assert result["files"] == 3 and result["empty_files"] == 0, result
    assert all(
        kill["lost_before_kill_s"] is not None and kill["gap_until_respawned_s"] is not None
        for kill in result["per_kill"]
    ), result


@pytest.fixture(scope="module")
def small_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return collected(tmp_path_factory.mktemp("collected") / "session", grasps=8, seed=2)


@pytest.mark.slow
def test_two_sessions_with_the_same_seed_write_the_same_dataset(small_session: Path, tmp_path: Path) -> None:
    assert content_checksum(collected(tmp_path / "again", grasps=8, seed=2)) == content_checksum(small_session)
    stamps = {r.sample_id: r.stamps_ns for r in DatasetReader(small_session).records}
    assert any(r.stamps_ns != stamps[r.sample_id] for r in DatasetReader(tmp_path / "again").records)


def test_the_strict_gripper_finds_every_part_at_its_nominal_width(small_session: Path) -> None:
    """W2: the simulated WSG looks for the part only within its clamping travel around the
    nominal width; grasping at width 0 found nothing on any object."""
    stats = json.loads((small_session / "session.json").read_text())["stats"]
    assert stats["skipped"] == 0 and stats["failed_draws"] == 0 and stats["grasps_done"] == 8


def test_no_grasp_is_written_where_an_open_finger_would_land_on_the_object(tmp_path: Path) -> None:
    """The unseen scene's cracker box is wider than the open gripper at most turns: the collector
    refuses those draws before the arm moves, and no grasp it writes is one where the simulated
    world finds an open finger already inside an object (its own ray cast, sim.grasp_contact),
    where the gel's image and the depth-map would describe a contact no gripper can make."""
    result = run_session(tmp_path / "session", grasps=6, seed=0, record=False, scene="scenes/ycb_unseen.yaml")
    assert result["exit_code"] == 0, result.get("collector_log")
    stats = result["session"]["stats"]
    assert stats["failed_draws"] > 0 and stats["grasps_done"] + stats["skipped"] == 6
    # A refused draw leaves the arm where it is: only a grasp it came down to is lifted from.
    assert not [line for line in result["collector_warnings"] if "retreat failed" in line]
    world = SimWorld.from_file("scenes/ycb_unseen.yaml")
    geometry = world.scene.gripper_geometry()
    for record in DatasetReader(tmp_path / "session").records:
        x, y, z, theta = record.grasp_pose
        tcp = pose_to_matrix(grasp_to_tcp_pose(x, y, z + geometry.tcp_to_gel_centre_m, theta))
        contact = world.grasp_contact(tcp, GRASP_FORCE_N, gap_fingers=())
        assert not any(finger.collision for finger in contact.fingers.values()), record.sample_id


@pytest.mark.parametrize("clearance", [-0.001, float("nan"), float("inf"), 0.055])
def test_a_clearance_no_draw_can_keep_is_refused_before_the_session_starts(tmp_path: Path, clearance: float) -> None:
    params = {"out": str(tmp_path / "session"), "finger_clearance_m": clearance}
    with pytest.raises(ValueError, match="finger_clearance_m must be in"):
        CollectorNode("collector", params, registry=Registry(tmp_path / "bus"))
    assert not (tmp_path / "session").exists()


def test_every_pair_whose_depth_map_presses_shows_the_press(small_session: Path) -> None:
    # The simulated gel presses only once its node has the grip from /gripper/state; a frame
    # captured before that is the untouched gel beside a depth-map that presses (a third of
    # the pairs did, when the settling time counted from the grasp reply).
    reader = DatasetReader(small_session)
    for record in reader.records:
        sample = reader.load(record)
        if np.mean(sample.depth_map_m < -0.001) > 0.05:
            touched = np.mean(deformation_map(sample.tactile_diff_rgb) > CONTACT_LEVELS)
            assert touched > 0.01, f"{record.sample_id}: the depth-map presses, the tactile image is untouched"


def test_the_information_ceiling_reproduces_the_session_and_orders_its_rungs(small_session: Path) -> None:
    result = information_ceiling(small_session, split="all")
    strict_json.dumps(result)  # as dtx sim ceiling --json prints it: strict JSON, or ValueError
    rungs = [result["rungs"][name] for name in RUNGS]
    assert result["reproduces_session"] and rungs[0]["n"] == 16
    # Knowing the true contact reproduces the images up to the sensor noise; knowing less costs.
    assert rungs[0]["ssim_model_mean"] > 0.98
    assert rungs[0]["ssim_model_mean"] >= rungs[1]["ssim_model_mean"] - 1e-3
    assert rungs[0]["dissimilarity_ratio"] < rungs[2]["dissimilarity_ratio"]
    assert "true contact, no relief" in format_table(result)
    # At another force the true contact is rendered pressed differently: flagged, not trusted.
    assert (
        information_ceiling(small_session, split="all", force_n=40.0)["rungs"][RUNGS[0]]["ssim_model_mean"]
        < rungs[0]["ssim_model_mean"]
    )


def test_the_information_ceiling_refuses_what_it_cannot_score(
    small_session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert sim_cli(["sim", "ceiling", str(tmp_path / "none")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert sim_cli(["sim", "ceiling", str(small_session), "--force-n", "-3"]) == 2
    assert "positive number of newtons" in capsys.readouterr().err
    with pytest.raises(CeilingError, match="positive number of newtons"):
        information_ceiling(small_session, force_n=0.0)
    with pytest.raises(CeilingError, match="positive number of newtons"):
        information_ceiling(small_session, force_n=float("nan"))
    with pytest.raises(ModelConfigError, match="unknown split"):
        information_ceiling(small_session, split="holdout")
    moved = tmp_path / "moved"
    shutil.copytree(small_session, moved)
    info = json.loads((moved / "dataset.json").read_text())
    (moved / "dataset.json").write_text(json.dumps({**info, "scene": "scenes/no_such_scene.yaml"}))
    with pytest.raises(CeilingError, match="no_such_scene.yaml.*cannot be loaded"):
        information_ceiling(moved)


def test_an_unwritable_output_stops_the_session_with_a_clear_error(tmp_path: Path) -> None:
    blocker = tmp_path / "not_a_directory"
    blocker.write_text("a file where the dataset should go")
    result = run_session(blocker / "session", grasps=2, seed=0, record=False)
    assert result["exit_code"] != 0
    assert any("cannot create the output directory" in line for line in result["collector_log"])
    assert blocker.read_text() == "a file where the dataset should go"


def replay(bag: Path, out: Path) -> subprocess.CompletedProcess[str]:
    with tempfile.TemporaryDirectory(prefix="dtxr") as bus_dir:
        return subprocess.run(
            [sys.executable, "-m", "dtx.cli", "launch", "launch/replay.yaml", f"bag:={bag}", f"out:={out}"],
            capture_output=True,
            text=True,
            timeout=300,
            env={**os.environ, "DTX_BUS_DIR": bus_dir},
        )


def test_replaying_the_shipped_bag_twice_gives_identical_datasets(tmp_path: Path) -> None:
    first, second = replay(SMALL_BAG, tmp_path / "a"), replay(SMALL_BAG, tmp_path / "b")
    assert first.returncode == 0, first.stdout[-2000:]
    assert second.returncode == 0, second.stdout[-2000:]
    report = check_dataset(tmp_path / "a")
    assert report.ok and report.samples == 8
    assert tree_digest(tmp_path / "a") == tree_digest(tmp_path / "b")
    # The bag's samples say which rule made their maps, and so does the dataset rebuilt from them.
    announced = [e.message for _, e in iter_envelopes(SMALL_BAG) if isinstance(e.message, msgs.DatasetSample)]
    assert len(announced) == 8 and {s.depth_map_method for s in announced} == {"surface"}
    assert DatasetReader(tmp_path / "a").info.depth_map_method == "surface"


def test_an_announced_sample_names_its_datasets_depth_map_rule(tmp_path: Path) -> None:
    """The replay's dataset.json takes the rule from the samples; a sample naming none (or an
    unknown one) would write a dataset.json no reader accepts, and one of another rule than its
    dataset's (a session resumed with another rule) would make it misname its maps: both refused."""
    sample = msgs.DatasetSample(
        sample_id="g00000_left",
        tactile_image=np.zeros((100, 100, 3), np.uint8),
        depth_range_m=[-0.005, 0.01],
        depth_crop_m=[0.024, 0.015, 0.019],
        depth_map_method="nearest_point",
    )
    writer = DatasetWriter(tmp_path / "nearest", dataset_info(sample))
    assert writer.info.depth_map_method == "nearest_point"
    sample.depth_map_method = "surface"
    with pytest.raises(DatasetError, match="holds nearest_point depth-maps, not surface ones"):
        write_samples(writer, [sample])
    assert len(writer) == 0
    for bad in ("", "median"):
        sample.depth_map_method = bad
        with pytest.raises(DatasetError, match="depth_map_method must be one of"):
            dataset_info(sample)


@pytest.fixture(scope="module")
def replayed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The shipped bag's dataset (surface maps), for the tests that make its maps again."""
    out = tmp_path_factory.mktemp("replayed") / "collected"
    assert replay(SMALL_BAG, out).returncode == 0
    return out


def test_depth_maps_made_again_from_the_recorded_model_poses(tmp_path: Path, replayed: Path) -> None:
    """A collected dataset records each model's pose in the gel frame and its maps' rule
    (surface): at full density the depth-maps come back bit for bit; thinned to the paper's
    densities they hold fewer points (a surface spans the gaps of its sampling, so not few)."""
    collected = DatasetReader(replayed)
    assert collected.info.depth_map_method == "surface"
    again = DatasetReader(redepth_dataset(replayed, tmp_path / "again", progress=False).root)
    sparse = DatasetReader(redepth_dataset(replayed, tmp_path / "sparse", 10.0, progress=False).root)
    y_far = np.float32(collected.info.depth_range_m[1])
    for record in collected.records:
        original = collected.load(record)
        np.testing.assert_array_equal(again.load(record.sample_id).depth_map_m, original.depth_map_m)
        np.testing.assert_array_equal(sparse.load(record.sample_id).tactile_rgb, original.tactile_rgb)
        thinned = sparse.load(record.sample_id).depth_map_m
        assert np.count_nonzero(thinned != y_far) < np.count_nonzero(original.depth_map_m != y_far)
    assert sparse.info == collected.info and [r.sample_id for r in sparse.records] == [
        r.sample_id for r in collected.records
    ]
    # The evaluator's density table makes the same maps in memory, and scores what the density
    # dataset scores.
    np.testing.assert_array_equal(
        depth_maps_at_density(collected, collected.records, 10.0),
        np.stack([sparse.load(r.sample_id).depth_map_m for r in collected.records]),
    )
    torch.manual_seed(0)
    generator = UNetGenerator(GeneratorConfig(ngf=8)).eval()
    depth_range_m = collected.info.depth_range_m
    result, _ = evaluate(generator, depth_range_m, collected.root, split="all", density=[10.0], progress=False)
    on_dataset = predict_dataset(generator, depth_range_m, sparse.root, split="all")
    assert result["density"][0]["ssim_mean"] == pytest.approx(ssim_rgb(on_dataset.truth, on_dataset.estimate).mean())
    # How much of the maps the thinned cloud leaves empty, counted as the inference node counts it.
    thinned_bins = surface_bins(on_dataset.depth_maps_m, depth_range_m[1]).mean()
    assert result["density"][0]["surface_bins_mean"] == pytest.approx(thinned_bins)
    assert thinned_bins < result["surface_bins_mean"] <= 10_000


def test_densities_made_again_in_two_processes_are_those_made_in_one(tmp_path: Path, replayed: Path) -> None:
    """Both densities in one pass each, shared out between two processes: the same files."""
    again = DatasetReader(redepth_dataset(replayed, tmp_path / "again", progress=False).root)
    sparse = DatasetReader(redepth_dataset(replayed, tmp_path / "sparse", 10.0, progress=False).root)
    shared = redepth_datasets(
        replayed, {None: tmp_path / "shared_full", 10.0: tmp_path / "shared_10"}, progress=False, jobs=2
    )
    for density, alone in ((None, again), (10.0, sparse)):
        assert tree_digest(shared[density].root) == tree_digest(alone.root), density
    with pytest.raises(DatasetError, match="jobs must be"):
        redepth_datasets(replayed, {10.0: tmp_path / "nojobs"}, progress=False, jobs=0)


def test_surface_maps_made_again_over_other_bins(tmp_path: Path, replayed: Path) -> None:
    """Over 50 x 50 bins the rule stays the dataset's, and a 50-bin reads the surface its 2 x 2
    100-bins read; bins the format cannot hold and a dataset made from no model are refused."""
    collected = DatasetReader(replayed)
    y_far = np.float32(collected.info.depth_range_m[1])
    coarse = DatasetReader(redepth_dataset(replayed, tmp_path / "coarse", bins=50, progress=False).root)
    assert (coarse.info.image_height, coarse.info.image_width) == (50, 50)
    assert coarse.info.depth_map_method == "surface"
    for record in collected.records:
        full, half = collected.load(record), coarse.load(record.sample_id)
        assert half.depth_map_m.shape == (50, 50) and half.tactile_rgb.shape == (50, 50, 3)
        # One 50-bin's centre is the corner of 2 x 2 100-bins: where it and they all hold the
        # surface, it is the mean of theirs (a smooth surface, within 20 um), but at edges and steps.
        blocks = full.depth_map_m.reshape(50, 2, 50, 2)
        surface = (half.depth_map_m != y_far) & (blocks != y_far).all(axis=(1, 3))
        assert np.mean(np.isclose(half.depth_map_m, blocks.mean(axis=(1, 3)), atol=2e-5)[surface]) > 0.95
    for bad in (0, 7, 2000, 50.5):
        with pytest.raises(DatasetError, match="bins must be"):
            redepth_dataset(replayed, tmp_path / f"bad{bad}", bins=bad, progress=False)
    write_synthetic_dataset(tmp_path / "synthetic", 2, seed=0, progress=False)
    with pytest.raises(DatasetError, match="records no depth-map crop"):
        redepth_dataset(tmp_path / "synthetic", tmp_path / "x", 10.0, progress=False)


def test_nearest_point_maps_made_again_from_a_surface_dataset(tmp_path: Path, replayed: Path) -> None:
    """The paper's rule from the same recorded poses: the dataset says so; thinned to the paper's
    densities a map holds a few bins; a 50-bin holds the minimum of its 2 x 2 100-bins."""
    nearest = {
        density: DatasetReader(writer.root)
        for density, writer in redepth_datasets(
            replayed, {None: tmp_path / "full", 10.0: tmp_path / "thin"}, progress=False, method="nearest_point"
        ).items()
    }
    coarse = DatasetReader(redepth_dataset(tmp_path / "full", tmp_path / "coarse", bins=50, progress=False).root)
    assert {r.info.depth_map_method for r in (*nearest.values(), coarse)} == {"nearest_point"}
    y_far = np.float32(nearest[None].info.depth_range_m[1])
    for record in nearest[None].records:
        full, thinned = (nearest[d].load(record.sample_id).depth_map_m for d in (None, 10.0))
        assert np.count_nonzero(thinned != y_far) < 0.1 * np.count_nonzero(full != y_far)
        # A 50-bin holds the points of 2 x 2 100-bins: its minimum is theirs, but where gap
        # filling made a bin up at one size and not at the other.
        block_min = full.reshape(50, 2, 50, 2).min(axis=(1, 3))
        assert np.mean(np.isclose(coarse.load(record.sample_id).depth_map_m, block_min, atol=1e-6)) > 0.95


def test_a_recorded_session_carries_the_transform_tree(tmp_path: Path) -> None:
    """Every frame the cell uses is in the bag as foxglove.FrameTransform, so Foxglove places
    the cameras, the tool, the gels and the object."""
    out = tmp_path / "session"
    result = run_session(out, grasps=2, seed=3, record=True)
    assert result["exit_code"] == 0
    bag = next(out.glob("session*.mcap"))
    frames = {
        (e.message.header.frame_id, e.message.child_frame_id)
        for _, e in iter_envelopes(bag)
        if e.topic in ("/tf", "/perception/object_pose")
    }
    assert frames == {
        ("world", "camera_left"),
        ("world", "camera_right"),
        ("world", "tcp"),
        ("tcp", "gel_left"),
        ("tcp", "gel_right"),
        ("world", "object"),
    }
    topics = bag_info(bag).topics
    assert (
        topics["/tf/foxglove"]["schema"]
        == topics["/perception/object_pose/foxglove"]["schema"]
        == "foxglove.FrameTransform"
    )


@pytest.mark.slow
def test_malformed_messages_at_every_endpoint_of_a_live_session_crash_nothing() -> None:
    """dtx bench fuzz at small size: every service and topic of a running collection session
    gets mutated messages the codec refuses; no node dies, every service answers each one with
    an error, and the session ends complete and sound."""
    parser = argparse.ArgumentParser()
    fuzz.add_arguments(parser)
    result = fuzz.run(parser.parse_args(["--messages", "200", "--grasps", "150", "--seed", "3"]))
    strict_json.dumps(result)  # as dtx bench fuzz --json prints it: strict JSON, or ValueError
    assert result["nodes_crashed"] == [] and result["respawns"] == 0 and result["nodes_checked"] >= 10, result
    services = [row for row in result["endpoints"] if row["kind"] == "service"]
    topics = [row for row in result["endpoints"] if row["kind"] == "topic"]
    assert {row["endpoint"] for row in services} >= {
        "/arm/move",
        "/gripper/command",
        "/perception/patch",
        "/perception/register",
    }
    assert all(row["sent"] == 200 and row["error_replies"] == 200 for row in services), services
    assert {"/gripper/state", "/camera_left/depth", "/gelsight_left/image"} <= {row["endpoint"] for row in topics}
    assert all(row["subscribers"] >= 1 for row in topics if row["endpoint"] == "/gripper/state")
    assert result["session_exit_code"] == 0 and result["dataset_check_ok"], result
    assert result["pairs"] == result["pairs_expected"] == 300
