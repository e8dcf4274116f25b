"""Touch-calibrated geometry (issue 28): the numerical core on constructed cells whose truth is
known, and ``dtx calibrate touches`` / ``dtx dataset redepth --calibration`` on bad input."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_json_output import strict_loads

from perception.touch_calibration import (
    TouchOffset,
    moved_depth_map,
    planar_transform,
    pose_error,
    profiled_fit,
    solve_cell,
    table_levelling,
)
from report.plan import QUICK
from report.sweeps.calibration import calibration_grasps
from report.workspace import Workspace

REPO = Path(__file__).resolve().parent.parent
FAR_M = 0.003


def test_a_map_moved_by_whole_bins_is_the_map_shifted() -> None:
    rng = np.random.default_rng(0)
    depth = rng.uniform(-0.001, 0.002, (20, 30)).astype(np.float32)
    moved = moved_depth_map(depth, (0.5, 0.25), np.array([0.5, 1.0, 0.0]), FAR_M)  # 2 columns, 2 rows
    np.testing.assert_allclose(moved[2:, 2:], depth[:-2, :-2], atol=1e-7)
    assert np.all(moved[:2] == np.float32(FAR_M)) and np.all(moved[:, :2] == np.float32(FAR_M))


def test_deeper_moves_only_the_surface() -> None:
    depth = np.full((10, 10), FAR_M, np.float32)
    depth[3:6, 3:6] = 0.0005
    moved = moved_depth_map(depth, (0.2, 0.2), np.array([0.0, 0.0, 0.3]), FAR_M)
    np.testing.assert_allclose(moved[3:6, 3:6], 0.0002, atol=1e-7)
    assert np.all(moved[depth == np.float32(FAR_M)] == np.float32(FAR_M))


@settings(max_examples=40, deadline=None, derandomize=True)
@given(
    st.floats(-0.19, 0.19),
    st.floats(-0.19, 0.19),
    st.floats(-0.08, 0.08),
    st.floats(0.5, 20.0),
    st.floats(0.5, 20.0),
)
def test_the_profiled_fit_finds_a_quadratic_minimum_and_its_curvature(
    x0: float, z0: float, y0: float, curvature_x: float, curvature_z: float
) -> None:
    """Within half a step of the grid's centre (where the coarser stages leave it)."""
    grid = (np.arange(-1, 2) * 0.4, np.arange(-1, 2) * 0.4, np.arange(-1, 2) * 0.1)
    x, z, y = np.meshgrid(*grid, indexing="ij")
    floor = 50.0
    ssd = floor + curvature_x * (x - x0) ** 2 + curvature_z * (z - z0) ** 2 + 3.0 * (y - y0) ** 2
    fit, information = profiled_fit(ssd, grid, pixels=100)
    assert fit[0] == pytest.approx(x0, abs=1e-6) and fit[1] == pytest.approx(z0, abs=1e-6)
    variance = ssd.min(axis=2)[np.unravel_index(np.argmin(ssd.min(axis=2)), (3, 3))] / 100
    assert information[0, 0] == pytest.approx(2 * curvature_x / (2 * variance), rel=1e-6)


def test_a_minimum_at_the_grid_edge_pins_nothing_there() -> None:
    grid = (np.arange(-1, 2) * 0.4, np.arange(-1, 2) * 0.4, np.arange(-1, 2) * 0.1)
    x, z, y = np.meshgrid(*grid, indexing="ij")
    ssd = 10.0 + (x - 1.0) ** 2 + (z - 0.1) ** 2 + y**2  # x's minimum lies beyond the grid
    _, information = profiled_fit(ssd, grid, pixels=10)
    assert information[0, 0] == 0.0 and information[1, 1] > 0.0


@settings(max_examples=20, deadline=None, derandomize=True)
@given(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-0.01, 0.01))
def test_levelling_lays_a_tilted_noisy_table_on_z_zero(tilt_x_deg: float, tilt_y_deg: float, height_m: float) -> None:
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.3, 0.3, (4000, 2))
    z = height_m + xy[:, 0] * np.tan(np.radians(tilt_x_deg)) + xy[:, 1] * np.tan(np.radians(tilt_y_deg))
    points = np.column_stack([xy, z + rng.normal(0, 0.001, len(z))])
    levelled = points @ table_levelling(points)[:3, :3].T + table_levelling(points)[:3, 3]
    plane = np.linalg.lstsq(np.column_stack([levelled[:, :2], np.ones(len(levelled))]), levelled[:, 2], rcond=None)[0]
    assert np.degrees(np.abs(plane[:2])).max() < 0.01 and abs(plane[2]) < 1e-4


def _box_model(size_m: tuple[float, float, float], spacing_m: float = 0.003) -> tuple[np.ndarray, np.ndarray]:
    """Points and outward normals on the sides and top of a box standing on z = 0."""
    points, normals = [], []
    sx, sy, sz = size_m
    for axis, sign in ((0, 1), (0, -1), (1, 1), (1, -1)):
        u = np.arange(-(sy if axis == 0 else sx) / 2, (sy if axis == 0 else sx) / 2, spacing_m)
        h = np.arange(0.0, sz, spacing_m)
        uu, hh = np.meshgrid(u, h)
        face = np.zeros((uu.size, 3))
        face[:, axis] = sign * (sx if axis == 0 else sy) / 2
        face[:, 1 - axis] = uu.ravel()
        face[:, 2] = hh.ravel()
        points.append(face)
        normals.append(np.tile(np.eye(3)[axis] * sign, (len(face), 1)))
    return np.concatenate(points), np.concatenate(normals)


def _box_mesh(size_m: tuple[float, float, float]) -> o3d.geometry.TriangleMesh:
    """The box of :func:`_box_model` as a mesh, what ``solve_cell`` measures camera points against."""
    sx, sy, sz = size_m
    return o3d.geometry.TriangleMesh.create_box(sx, sy, sz).translate((-sx / 2, -sy / 2, 0.0))


def _touches_on(
    model: tuple[np.ndarray, np.ndarray], truth: np.ndarray, predicted: np.ndarray, rng: np.random.Generator
) -> list[TouchOffset]:
    """Touches at the box's side faces: gel y along the face normal, gel z vertical; each
    offset is the in-plane move from the predicted to the true contact, plus 0.05 mm noise."""
    touches = []
    points, normals = model
    sides = np.flatnonzero(np.abs(normals[:, 2]) < 0.5)
    for index in rng.choice(sides, 60, replace=False):
        contact_true = truth[:3, :3] @ points[index] + truth[:3, 3]
        contact_predicted = predicted[:3, :3] @ points[index] + predicted[:3, 3]
        normal = truth[:3, :3] @ normals[index]
        gel = np.eye(4)
        gel[:3, 1] = -normal
        gel[:3, 2] = [0.0, 0.0, -1.0]
        gel[:3, 0] = np.cross(gel[:3, 1], gel[:3, 2])
        gel[:3, 3] = contact_true
        offset = gel[:3, [0, 2]].T @ (contact_true - contact_predicted) * 1e3 + rng.normal(0, 0.05, 2)
        touches.append(TouchOffset(offset, np.eye(2) * 400.0, contact_predicted, gel))
    return touches


@settings(max_examples=8, deadline=None, derandomize=True)
@given(
    st.lists(st.floats(-2.0, 2.0), min_size=2, max_size=2),
    st.lists(st.floats(-2.0, 2.0), min_size=2, max_size=2),
    st.floats(-0.08, 0.08),
    st.floats(-0.08, 0.08),
)
def test_the_cell_fit_recovers_each_cameras_place_and_turn(
    left_mm: list[float], right_mm: list[float], left_deg: float, right_deg: float
) -> None:
    """Two cameras see two boxes, each camera displaced on the table; the boxes were registered
    from both, so each sits between the two errors. The fit finds every camera's correction."""
    rng = np.random.default_rng(2)
    sizes = {"a": (0.06, 0.04, 0.1), "b": (0.05, 0.08, 0.06)}
    models = {o: _box_model(size) for o, size in sizes.items()}
    truth = {"a": planar_transform(0.3, -150.0, 20.0), "b": planar_transform(-0.5, 160.0, -30.0)}
    camera_error = {
        "left": planar_transform(np.radians(left_deg), *left_mm),
        "right": planar_transform(np.radians(right_deg), *right_mm),
    }
    # the registration, from both cameras' points, lands between their two errors
    half = {
        c: planar_transform(np.radians(d) / 2, *(np.array(m) / 2))
        for c, d, m in (("l", left_deg, left_mm), ("r", right_deg, right_mm))
    }
    predicted = {o: half["l"] @ half["r"] @ truth[o] for o in truth}
    views = {}
    for camera, error in camera_error.items():
        views[camera] = {}
        for o in truth:
            model_points = models[o][0]
            seen = model_points[model_points[:, 1] * (1 if camera == "left" else -1) < 0.01]  # its side
            world = seen @ truth[o][:3, :3].T + truth[o][:3, 3]
            views[camera][o] = world @ error[:3, :3].T + error[:3, 3] + rng.normal(0, 0.0005, world.shape)
    touches = {o: _touches_on(models[o], truth[o], predicted[o], rng) for o in truth}
    cell = solve_cell(touches, predicted, views, {o: _box_mesh(size) for o, size in sizes.items()})
    for camera, error in camera_error.items():
        found = cell.cameras[camera] @ error  # the fit undoes the camera's error
        assert np.linalg.norm(found[:2, 3]) * 1e3 < 0.1, camera
        assert abs(np.degrees(np.arctan2(found[1, 0], found[0, 0]))) < 0.01, camera
    for o in truth:  # each box's centre where it stands
        assert np.linalg.norm(cell.objects[o][:2, 3] - truth[o][:2, 3]) * 1e3 < 0.1, o


def test_pose_error_reads_a_camera_offset_as_the_scene_states_it() -> None:
    offset = planar_transform(np.radians(0.05), 1.5, -1.0)
    nominal = planar_transform(0.2, 100.0, -750.0)
    error_mm, error_deg = pose_error(nominal, nominal @ offset)
    assert error_mm == pytest.approx(np.hypot(1.5, 1.0), rel=1e-9)
    assert error_deg == pytest.approx(0.05, rel=1e-6)


# -- the commands on a short session ---------------------------------------------------------


def _dtx(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "dtx.cli", *args], cwd=REPO, capture_output=True, text=True, timeout=900
    )


@pytest.fixture(scope="module")
def short_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 10-grasp simulated session recording every topic (its registration frames too)."""
    out = tmp_path_factory.mktemp("touch") / "session"
    env_domain = f"touch{id(out) % 100000}"
    result = subprocess.run(
        [sys.executable, "-m", "dtx.cli", "launch", "launch/collect_sim.yaml", f"out:={out}", "grasps:=10", "seed:=5"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=900,
        env={**__import__("os").environ, "DTX_DOMAIN": env_domain},
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return out


def test_too_few_touches_is_refused_with_the_count_and_nothing_written(short_session: Path, tmp_path: Path) -> None:
    out = tmp_path / "calibration"
    out.mkdir()
    (out / "camera_left.yaml").write_text("the lab's own\n")
    result = _dtx("calibrate", "touches", str(short_session), "--out", str(out), "--force")
    assert result.returncode == 1
    assert "training touches show a contact" in result.stderr and "needs >= 30" in result.stderr
    assert (out / "camera_left.yaml").read_text() == "the lab's own\n"


def test_an_existing_calibration_is_kept_without_force(short_session: Path, tmp_path: Path) -> None:
    out = tmp_path / "calibration"
    out.mkdir()
    result = _dtx("calibrate", "touches", str(short_session), "--out", str(out))
    assert result.returncode == 1 and "--force" in result.stderr


def test_a_session_without_its_camera_frames_is_refused(short_session: Path, tmp_path: Path) -> None:
    bare = tmp_path / "bare"
    bare.mkdir()
    for name in ("dataset.json", "manifest.jsonl"):
        (bare / name).write_bytes((short_session / name).read_bytes())
    result = _dtx("calibrate", "touches", str(bare), "--out", str(tmp_path / "c"))
    assert result.returncode == 1 and "session bag" in result.stderr


def test_redepth_refuses_a_calibration_for_other_cameras(short_session: Path, tmp_path: Path) -> None:
    calibration = tmp_path / "calibration"
    calibration.mkdir()
    for side in ("left", "right"):
        text = (REPO / "launch" / "calibration" / f"camera_{side}.yaml").read_text()  # a Kinect with distortion
        (calibration / f"camera_{side}.yaml").write_text(text.replace("fx: 365.5", "fx: 366.0"))
    result = _dtx(
        "dataset", "redepth", str(short_session), "--calibration", str(calibration), "--out", str(tmp_path / "o")
    )
    assert result.returncode == 1 and "describes another camera" in result.stderr and "fx" in result.stderr
    assert not (tmp_path / "o").exists()


def _own_calibration(session: Path, out: Path) -> Path:
    """A calibration directory holding the extrinsics ``session``'s registrations used."""
    from dataset.touch_calibration import registration_frames
    from drivers.depth_camera.base import Calibration, calibration_yaml

    out.mkdir()
    for frame_id, frames in registration_frames(session).items():
        image = frames[-1]
        own = Calibration(frame_id.removeprefix("camera_"), image.intrinsics, image.camera_to_world)
        (out / f"{frame_id}.yaml").write_text(calibration_yaml(own, "as recorded"))
    return out


def test_a_session_too_short_to_place_its_objects_keeps_their_registered_places(
    short_session: Path, tmp_path: Path
) -> None:
    """Ten grasps leave fewer touches than placing the objects needs: the maps are cut at the
    registered places and the command says why, and where each object went."""
    calibration = _own_calibration(short_session, tmp_path / "calibration")
    result = _dtx(
        "dataset", "redepth", str(short_session), "--calibration", str(calibration), "--out", str(tmp_path / "o")
    )
    assert result.returncode == 0, result.stderr
    assert "keep their registered places" in result.stderr and "needs >= 30" in result.stderr
    # each object: where the registration moved it, and (the scene's truth known) how far it is
    assert result.stdout.count("from its recorded pose; ADD-S") == 3, result.stdout
    assert (tmp_path / "o" / "manifest.jsonl").exists()


def test_a_calibration_places_the_objects_of_its_own_session_only(short_session: Path, tmp_path: Path) -> None:
    """``placements.json`` (the calibration's fit of its session's objects) is taken by that
    session's redepth, and not by another session's; a damaged one is refused by name."""
    import shutil

    from dataset.reader import DatasetReader
    from dataset.records import DatasetError
    from dataset.registered_again import PLACEMENTS_FILE, objects_placed, placements_file

    calibration = _own_calibration(short_session, tmp_path / "calibration")
    shift = np.eye(4)
    shift[0, 3] = 0.001
    moved = {r.object_name: np.array(r.model_to_world) @ shift for r in DatasetReader(short_session).records}
    (calibration / PLACEMENTS_FILE).write_text(placements_file(short_session, moved))
    placed, how = objects_placed(short_session, calibration)
    assert "own fit of this session" in how and placed.keys() == moved.keys()
    assert all(np.array_equal(placed[name], moved[name]) for name in moved)
    result = _dtx(
        "dataset", "redepth", str(short_session), "--calibration", str(calibration), "--out", str(tmp_path / "o")
    )
    assert result.returncode == 0, result.stderr
    assert "placed by the calibration's own fit" in result.stdout
    assert result.stdout.count("moved 1.00 mm 0.00 deg from its recorded pose") == 3, result.stdout
    # Another session (one grasp fewer) registers its objects again.
    other = tmp_path / "other"
    shutil.copytree(short_session, other)
    manifest = (other / "manifest.jsonl").read_text().splitlines(keepends=True)
    (other / "manifest.jsonl").write_text("".join(manifest[:-2]))
    with pytest.warns(UserWarning, match="keep their registered places"):
        _, how = objects_placed(other, calibration)
    assert "registered again" in how
    for damaged in ("not json", "{}", '{"session_records_sha256": 1, "objects": []}'):
        (calibration / PLACEMENTS_FILE).write_text(damaged)
        with pytest.raises(DatasetError, match="not a placements file"):
            objects_placed(short_session, calibration)


def test_registered_again_with_the_cameras_own_calibration_gives_the_collected_maps(
    short_session: Path, tmp_path: Path
) -> None:
    """Registered again from the recorded frames with their own extrinsics (and no turn offered to
    the touches), every map comes back bit for bit: the calibrated path is the patch
    extractor's, not an approximation of it."""
    from dataset.reader import DatasetReader
    from dataset.redepth import redepth_dataset
    from dataset.registered_again import calibrated_frames, register_again

    frames = calibrated_frames(short_session, _own_calibration(short_session, tmp_path / "calibration"))
    registered = register_again(short_session, frames, by_touches=False)
    redepth_dataset(short_session, tmp_path / "o", registered=registered, progress=False)
    collected, again = DatasetReader(short_session), DatasetReader(tmp_path / "o")
    for record in collected.records:
        np.testing.assert_array_equal(again.load(record.sample_id).depth_map_m, collected.load(record).depth_map_m)
    assert json.loads((tmp_path / "o" / "dataset.json").read_text())["scene"] == collected.info.scene


def test_the_touches_choose_an_objects_true_turn_over_its_half_turn(short_session: Path) -> None:
    """The mustard bottle half a turn round about its centre is what the cameras see of it too;
    its touches tell the two apart, whichever is offered as the registered one."""
    from dataset.reader import DatasetReader
    from dataset.splits import split_records
    from dataset.touches import TouchRenderer
    from dataset.turns import TurnJudge
    from perception.registration import sample_model_cloud
    from sim.world import SimWorld
    from workcell.scene import load_scene

    reader = DatasetReader(short_session)
    scene = load_scene(reader.info.scene)
    world = SimWorld(scene)
    name = "mustard_bottle"
    truth = world.object_to_world[[o.name for o in scene.objects].index(name)]
    centre = sample_model_cloud(scene.mesh(name), seed=0).points_m.mean(axis=0)
    centre_world = truth[:3, :3] @ centre + truth[:3, 3]
    half_turn = planar_transform(np.pi, *(1e3 * (centre_world[:2] - [[-1, 0], [0, -1]] @ centre_world[:2])))
    turned = half_turn @ truth
    train = split_records(reader.records, reader.info.split_seed)["train"]
    judge = TurnJudge(reader, train, TouchRenderer(reader, scene).residuals)
    np.testing.assert_array_equal(judge.choose(name, [turned, truth]), truth)
    np.testing.assert_array_equal(judge.choose(name, [truth, turned]), truth)
    np.testing.assert_array_equal(judge.choose(name, [truth]), truth)


def test_the_frames_choose_a_cans_turn_about_its_axis(short_session: Path) -> None:
    """A can looks alike to the cameras at every turn about its axis; its side, a few tenths of a
    millimetre out of round, is what its frames tell the turns apart by: a quarter turn loses to
    the true one, and a placed can 1.5 deg off is turned back to within 0.5 deg (from the ten
    grasps of this session; 0.04 deg on the demo session)."""
    from dataset.reader import DatasetReader
    from dataset.redepth import model_cloud
    from dataset.splits import split_records
    from dataset.touches import TouchRenderer
    from dataset.turns import TurnJudge, turned_about_vertical
    from perception.touch_calibration import pose_error
    from sim.world import SimWorld
    from workcell.scene import load_scene

    reader = DatasetReader(short_session)
    scene = load_scene(reader.info.scene)
    name = "master_chef_can"
    truth = SimWorld(scene).object_to_world[[o.name for o in scene.objects].index(name)]
    centre = truth[:3, :3] @ model_cloud(scene, name).mean(axis=0) + truth[:3, 3]
    train = split_records(reader.records, reader.info.split_seed)["train"]
    judge = TurnJudge(reader, train, TouchRenderer(reader, scene).residuals)
    quarter_turn = turned_about_vertical(truth, centre, 0.5 * np.pi)
    np.testing.assert_array_equal(judge.choose(name, [quarter_turn, truth]), truth)
    refined = judge.refined(name, turned_about_vertical(truth, centre, np.radians(1.5)))
    assert pose_error(refined, truth)[1] < 0.5
    # Frames that tell nothing (every turn's residual alike) leave a placed object as it is.
    untold = TurnJudge(reader, train, lambda records: np.ones(len(records)))
    np.testing.assert_array_equal(untold.refined(name, truth), truth)


def test_touches_fitted_and_drawn_in_two_processes_are_those_of_one(short_session: Path) -> None:
    """``--jobs``: every touch is fitted and drawn alone, so sharing them out changes nothing."""
    from dataset.reader import DatasetReader
    from dataset.redepth import depth_map_params
    from dataset.touches import TouchPool, TouchRenderer, records_cut_at

    reader = DatasetReader(short_session)
    params, scene = depth_map_params(reader)
    name = reader.records[0].object_name
    records = [r for r in reader.records if r.object_name == name]
    moved = planar_transform(0.002, 0.4, -0.3) @ np.array(records[0].model_to_world)
    records = records_cut_at(records, {name: moved}, scene, params)
    renderer = TouchRenderer(reader, scene)
    alone, alone_residuals = renderer.touches(records), renderer.residuals(records)
    with TouchPool(short_session, 2) as pool:
        shared, shared_residuals = pool.touches(records), pool.residuals(records)
    np.testing.assert_array_equal(shared_residuals, alone_residuals)
    assert alone_residuals.shape == (len(records),) and (alone_residuals > 0).all()
    assert any(t is not None for t in alone)
    assert [t is None for t in shared] == [t is None for t in alone]
    for a, b in zip(alone, shared):
        if a is not None and b is not None:
            np.testing.assert_array_equal(a.offset_gel_mm, b.offset_gel_mm)
            np.testing.assert_array_equal(a.information_gel, b.information_gel)


def test_a_shorter_session_takes_each_objects_first_grasps_in_turn() -> None:
    from dataset.records import DatasetError, SampleRecord
    from dataset.touch_calibration import _first_grasps

    def record(name: str, grasp: int, finger: str) -> SampleRecord:
        files = {
            k: f"{k}/g{grasp}_{finger}.{'npy' if k == 'depth' else 'png'}" for k in ("tactile", "tactile_diff", "depth")
        }
        return SampleRecord(
            f"g{grasp}_{finger}", name, grasp, finger, (0, 0, 0, 0), {}, 1.0, files, dict.fromkeys(files, "")
        )

    records = [
        record(name, g, f)
        for name, ids in (("a", range(0, 5)), ("b", range(5, 8)))
        for g in ids
        for f in ("left", "right")
    ]
    chosen = _first_grasps(records, 3)
    assert sorted({(r.object_name, r.grasp_id) for r in chosen}) == [("a", 0), ("a", 1), ("b", 5)]
    assert len(chosen) == 6  # both fingers of each grasp
    assert len(_first_grasps(records, 100)) == len(records)
    with pytest.raises(DatasetError, match="grasps"):
        _first_grasps(records, 0)


def test_the_report_is_strict_json_with_and_without_the_truth() -> None:
    """What ``dtx calibrate touches --json`` prints and writes to report.json."""
    from dataset.touch_calibration import TouchCalibration
    from msgs import DepthImage, strict_json

    rng = np.random.default_rng(3)
    models = {"a": _box_model((0.06, 0.04, 0.1))}
    truth = {"a": planar_transform(0.2, -100.0, 10.0)}
    error = planar_transform(np.radians(0.04), 1.0, -1.5)
    seen = models["a"][0] @ truth["a"][:3, :3].T + truth["a"][:3, 3]
    views = {"camera_left": {"a": seen @ error[:3, :3].T + error[:3, 3]}, "camera_right": {"a": np.zeros((0, 3))}}
    touches = {"a": _touches_on(models["a"], truth["a"], truth["a"], rng)}
    cell = solve_cell(touches, truth, views, {"a": _box_mesh((0.06, 0.04, 0.1))})
    corrections = {c: cell.cameras[c] for c in views}
    calibrated = {c: DepthImage(camera_to_world=corrections[c]) for c in views}
    result = TouchCalibration(cell, corrections, calibrated, {"a": 60}, 3)
    for truth_given in (None, {"camera_left": np.linalg.inv(error), "camera_right": np.eye(4)}):
        report = strict_loads(strict_json.dumps(result.report(truth_given)))
        assert report["cameras"]["right"]["point_residual_mm"] is None  # no point on a model
        assert ("error_mm" in report["cameras"]["left"]) == (truth_given is not None)


def test_the_report_sweep_states_the_given_extrinsics_and_names_what_it_refused(
    short_session: Path, tmp_path: Path
) -> None:
    """dtx report accuracy-time's calibration_grasps on a collected session: the uncalibrated
    reference carries the scene's own offset (ycb_three: 1.5, -1.0, 1.2 mm on the left), and a
    calibration from too few touches is a point without accuracy that says why, not a crash."""
    plan = dataclasses.replace(QUICK, calibration_grasps=(3, 1000))
    points = calibration_grasps(Workspace(tmp_path, plan, [short_session]))
    reference, *calibrated = points
    assert reference["setting"].startswith("none")
    assert reference["accuracy"] == pytest.approx(np.linalg.norm([1.5, -1.0, 1.2]), abs=0.5)
    assert 0 < reference["renderer_ratio"] < 2
    assert [p["setting"] for p in calibrated][0] == "3 grasps"
    for point in calibrated:
        assert np.isnan(point["accuracy"]) and "touches" in point["refused"]
