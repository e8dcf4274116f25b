"""Scene files: the shipped scenes load; every kind of bad input is refused with an error that
names the file, the key and the allowed values."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

from sim.effects import EFFECTS
from sim.shapes import write_shapes
from sim.world import SimWorld
from workcell.scene import SceneError, load_scene

REPO = Path(__file__).resolve().parent.parent
SCENES = sorted((REPO / "scenes").glob("*.yaml"))


def _ideal() -> dict:
    return yaml.safe_load((REPO / "scenes" / "ideal.yaml").read_text())


def _write(tmp_path: Path, data: dict, name: str = "bad.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


def _error(tmp_path: Path, data: dict) -> SceneError:
    path = _write(tmp_path, data)
    with pytest.raises(SceneError) as info:
        SimWorld.from_file(path)
    err = info.value
    assert str(path) in str(err)  # names the file
    return err


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_shipped_scenes_load(path: Path) -> None:
    scene = SimWorld.from_file(path).scene
    assert len(scene.cameras) == 2
    assert scene.objects


def test_required_scenes_exist() -> None:
    names = {p.stem for p in SCENES}
    assert {"ycb_three", "ideal"} <= names
    assert load_scene(REPO / "scenes" / "ideal.yaml").effects == []
    ycb = load_scene("scenes/ycb_three.yaml")
    assert len(ycb.objects) == 3 and all(o.mesh.startswith("assets/ycb/") for o in ycb.objects)
    # one scene per effect family covers every registered effect except the GelSight ones
    covered = set()
    for p in SCENES:
        if p.stem.startswith("effects_"):
            covered |= {e.name for e in load_scene(p).effects}
    assert {n for n, e in EFFECTS.items() if e.family != "gelsight"} <= covered


def test_the_unseen_scene_has_the_other_ycb_meshes_and_the_same_sensors() -> None:
    three, unseen = load_scene("scenes/ycb_three.yaml"), load_scene("scenes/ycb_unseen.yaml")
    shipped = {f"assets/ycb/{p.name}" for p in (REPO / "assets" / "ycb").glob("*.obj")}
    assert {o.mesh for o in unseen.objects} == shipped - {o.mesh for o in three.objects}
    assert {o.name for o in unseen.objects} == {"cracker_box", "power_drill"}
    assert (unseen.effects, unseen.gripper, unseen.gelsight) == (three.effects, three.gripper, three.gelsight)
    for mine, theirs in zip(unseen.cameras, three.cameras, strict=True):
        assert mine.name == theirs.name and (mine.camera_to_world == theirs.camera_to_world).all()


def test_generated_shapes_are_usable_scene_objects(tmp_path: Path) -> None:
    """Closed, manifold, resting on their lowest point: a scene with every shape loads."""
    data = _ideal()
    spots_m = [(-0.2, -0.15), (0.0, -0.15), (0.2, -0.15), (-0.2, 0.15), (0.0, 0.15), (0.2, 0.15), (0.0, 0.0)]
    data["objects"] = [
        {"name": path.stem, "mesh": str(path), "pose": {"x_m": x_m, "y_m": y_m}}
        for path, (x_m, y_m) in zip(write_shapes(tmp_path), spots_m, strict=True)
    ]
    data["workspace"] = {"min_m": [-0.4, -0.3, 0.0], "max_m": [0.4, 0.3, 0.5]}
    scene = load_scene(_write(tmp_path, data, "shapes.yaml"))
    assert len(scene.objects) == 7
    with pytest.raises(ValueError, match="no generated shape named mug"):
        write_shapes(tmp_path, ["mug"])


def test_kinect_intrinsics() -> None:
    cam = load_scene("scenes/ycb_three.yaml").cameras[0]
    assert (cam.width, cam.height) == (512, 424)
    assert cam.fx == pytest.approx(365.5) and cam.cx == pytest.approx(254.9) and cam.cy == pytest.approx(205.4)


def test_unknown_key(tmp_path: Path) -> None:
    data = _ideal()
    data["lights"] = []
    err = _error(tmp_path, data)
    assert err.key == "lights" and "cameras" in str(err.allowed)


def test_unknown_nested_key(tmp_path: Path) -> None:
    data = _ideal()
    data["objects"][0]["pose"]["roll_deg"] = 3
    err = _error(tmp_path, data)
    assert err.key == "objects[0].pose.roll_deg" and "yaw_deg" in str(err.allowed)


def test_unknown_effect(tmp_path: Path) -> None:
    data = _ideal()
    data["effects"] = [{"name": "motion_blur"}]
    err = _error(tmp_path, data)
    assert err.key == "effects[0].name" and "axial_noise" in str(err.allowed)


def test_unknown_effect_parameter(tmp_path: Path) -> None:
    data = _ideal()
    data["effects"] = [{"name": "axial_noise", "sigma": 3}]
    err = _error(tmp_path, data)
    assert err.key == "effects[0].sigma" and "a0_mm" in str(err.allowed)


def test_missing_mesh(tmp_path: Path) -> None:
    data = _ideal()
    data["objects"][0]["mesh"] = "assets/ycb/NoSuchThing.obj"
    err = _error(tmp_path, data)
    assert err.key == "objects[0].mesh" and "not found" in str(err)


def test_empty_mesh(tmp_path: Path) -> None:
    mesh = tmp_path / "empty.obj"
    mesh.write_text("# nothing here\n")
    data = _ideal()
    data["objects"][0]["mesh"] = str(mesh)
    err = _error(tmp_path, data)
    assert err.key == "objects[0].mesh" and "empty" in str(err) and "manifold" in str(err.allowed)


def test_non_manifold_mesh(tmp_path: Path) -> None:
    # three triangles sharing the edge (1, 2): not edge-manifold
    mesh = tmp_path / "fin.obj"
    mesh.write_text(
        "v 0 0 0\nv 0.05 0 0\nv 0 0.05 0\nv 0 0 0.05\nv 0.05 0.05 0.05\nv -0.05 0.02 0.03\n"
        "f 1 2 3\nf 2 3 4\nf 2 3 5\nf 2 3 6\n"
    )
    data = _ideal()
    data["objects"][0]["mesh"] = str(mesh)
    err = _error(tmp_path, data)
    assert err.key == "objects[0].mesh" and "non-manifold" in str(err)


def test_camera_looking_away(tmp_path: Path) -> None:
    data = _ideal()
    data["cameras"][1]["pose"] = {"position_m": [0.0, 1.0, 0.75], "look_at_m": [0.0, 3.0, 2.0]}
    err = _error(tmp_path, data)
    assert err.key == "cameras[1].pose" and "sees nothing" in str(err) and "workspace" in str(err.allowed)


def test_object_outside_workspace(tmp_path: Path) -> None:
    data = _ideal()
    data["objects"][2]["pose"]["x_m"] = 0.5
    err = _error(tmp_path, data)
    assert err.key == "objects[2].pose" and "workspace" in str(err.allowed)


@pytest.mark.parametrize(
    "mutate, key",
    [
        (lambda d: d["effects"].append({"name": "axial_noise", "scale": 50}), "effects[0].scale"),
        (lambda d: d["effects"].append({"name": "quantisation", "step_mm": -1}), "effects[0].step_mm"),
        (
            lambda d: d["effects"].append({"name": "missing_returns", "min_range_m": 2.0, "max_range_m": 1.0}),
            "effects[0].max_range_m",
        ),
        (
            lambda d: d["effects"].append({"name": "extrinsic_offset", "rotation_deg": [0, 0, 45]}),
            "effects[0].rotation_deg[2]",
        ),
        (lambda d: d["objects"][1]["relief"][0].update(depth_mm=5.0), "objects[1].relief[0].depth_mm"),
        (lambda d: d["objects"][1]["relief"][0].update(pitch_mm=0.01), "objects[1].relief[0].pitch_mm"),
        (lambda d: d["gripper"].update(elastomer_thickness_mm=-2), "gripper.elastomer_thickness_mm"),
        (lambda d: d["gripper"].update(grasp_force_n=0.0), "gripper.grasp_force_n"),
        (lambda d: d["gripper"].update(grasp_force_n="ten"), "gripper.grasp_force_n"),
        (lambda d: d["cameras"][0]["intrinsics"].update(fx=0.0), "cameras[0].intrinsics.fx"),
        (lambda d: d["gelsight"].update(mm_per_px=5.0), "gelsight.mm_per_px"),
    ],
    ids=[
        "axial_scale",
        "quant_step",
        "range_order",
        "extrinsic_rotation",
        "relief_depth",
        "relief_pitch",
        "elastomer",
        "grasp_force_zero",
        "grasp_force_text",
        "fx",
        "mm_per_px",
    ],
)
def test_parameter_out_of_range(tmp_path: Path, mutate, key: str) -> None:
    data = copy.deepcopy(_ideal())
    data["effects"] = []
    mutate(data)
    err = _error(tmp_path, data)
    assert err.key == key
    assert err.allowed is not None and ("[" in str(err.allowed) or "(" in str(err.allowed))


def test_unknown_camera_in_effect(tmp_path: Path) -> None:
    data = _ideal()
    data["effects"] = [{"name": "extrinsic_offset", "camera": "middle"}]
    err = _error(tmp_path, data)
    assert err.key == "effects[0].camera" and "left" in str(err.allowed)


def test_missing_file() -> None:
    with pytest.raises(SceneError, match="not found"):
        load_scene("scenes/does_not_exist.yaml")


def test_gelsight_effects_validated(tmp_path: Path) -> None:
    data = _ideal()
    data["effects"] = [{"name": "sensor_noise", "sigma_levels": -3.0}]
    err = _error(tmp_path, data)
    assert err.key == "effects[0].sigma_levels"
    data["effects"] = [{"name": "markers", "colour": "red"}]
    err = _error(tmp_path, data)
    assert err.key == "effects[0].colour" and "pitch_mm" in str(err.allowed)


def test_an_objects_mesh_is_found_by_name() -> None:
    scene = load_scene("scenes/ycb_three.yaml")
    assert scene.mesh("mustard_bottle") == "assets/ycb/MustardBottle.obj"
    with pytest.raises(SceneError, match="no object with a mesh named 'mug'"):
        scene.mesh("mug")
