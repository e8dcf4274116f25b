"""Scene files: the workcell (table, objects, cameras, gripper, GelSight) and the effects a
simulation of it calls for.

A scene is a YAML file (see ``scenes/README.md`` for the schema). :func:`load_scene` reads
and validates the workcell completely; every problem raises a :class:`SceneError` whose text
names the file, the key (a dotted path such as ``objects[1].relief[0].pitch_mm``) and the
allowed values. The lab nodes read it for the objects' meshes and the gripper geometry. The
parts it describes (table, objects, cameras, gripper, GelSight) are ``workcell.parts``.

Effects are listed here by name, with their parameters as written: which effects exist and
what their parameters mean is the simulator's (``sim.effects``), which checks them, with the
same kind of error, when it reads the scene (``SimWorld.from_file``). A lab node never runs an
effect, so it does not need to know them.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from workcell.kinematics import GripperGeometry
from workcell.parts import RELIEF_KINDS, CameraSpec, GelSightSpec, GripperSpec, ObjectSpec, ReliefSpec, TableSpec

REPO_ROOT = Path(__file__).resolve().parent.parent


class SceneError(ValueError):
    """A scene file is invalid: the message names the file, the key and the allowed values."""

    def __init__(self, file: str | os.PathLike | None, key: str, problem: str, allowed: Any = None):
        self.file = str(file) if file is not None else "<scene>"
        self.key = key
        self.problem = problem
        self.allowed = allowed
        text = f"{self.file}: {key}: {problem}"
        if allowed is not None:
            text += f" (allowed: {allowed})"
        super().__init__(text)


# --------------------------------------------------------------------------------------
# Scene dataclasses (the workcell's parts are workcell.parts)
# --------------------------------------------------------------------------------------


@dataclasses.dataclass
class EffectSpec:
    """An effect the scene calls for: its parameters as written (``sim.effects`` fills in the
    defaults when the simulator reads the scene) and where it is in the file."""

    name: str
    params: dict[str, Any]
    camera: str | None = None  # depth effects: restricted to this camera (None = all)
    key: str = "effects"  # its place in the file, e.g. "effects[2]", for error messages


@dataclasses.dataclass
class Scene:
    path: str
    name: str
    workspace_min_m: np.ndarray
    workspace_max_m: np.ndarray
    table: TableSpec
    objects: list[ObjectSpec]
    cameras: list[CameraSpec]
    gripper: GripperSpec
    gelsight: GelSightSpec
    effects: list[EffectSpec]
    seed: int = 0

    def effect(self, name: str, camera: str | None = None) -> EffectSpec | None:
        """The effect ``name`` (for ``camera`` when given), or None when not called for."""
        for spec in self.effects:
            if spec.name == name and (camera is None or spec.camera in (None, camera)):
                return spec
        return None

    def camera(self, name: str) -> CameraSpec:
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise SceneError(self.path, "cameras", f"no camera named {name!r}", [c.name for c in self.cameras])

    def mesh(self, object_name: str) -> str:
        """The mesh path of the object named ``object_name`` (SceneError if it has none)."""
        for obj in self.objects:
            if obj.name == object_name and obj.mesh:
                return obj.mesh
        raise SceneError(
            self.path,
            "objects",
            f"no object with a mesh named {object_name!r}",
            [o.name for o in self.objects if o.mesh],
        )

    def gripper_geometry(self) -> GripperGeometry:
        """The :class:`GripperGeometry` of this scene's gripper; its sensed area is the GelSight
        image's field of view (``image_width`` x ``image_height`` pixels of ``mm_per_px``,
        centred on the gel)."""
        gs = self.gelsight
        return GripperGeometry(
            tcp_to_gel_centre_m=self.gripper.tcp_to_gel_centre_m,
            gel_size_m=(self.gripper.gel_size_m[0], self.gripper.gel_size_m[1]),
            elastomer_thickness_m=self.gripper.elastomer_thickness_m,
            max_width_m=self.gripper.max_width_m,
            sensed_area_m=(gs.image_width * gs.mm_per_px * 1e-3, gs.image_height * gs.mm_per_px * 1e-3),
        )


# --------------------------------------------------------------------------------------
# Validation helpers
# --------------------------------------------------------------------------------------


class SceneReader:
    """Checks one value of a scene file at a time, raising SceneError with the file and key."""

    def __init__(self, file: str):
        self.file = file

    def fail(self, key: str, problem: str, allowed: Any = None) -> None:
        raise SceneError(self.file, key, problem, allowed)

    def mapping(self, value: Any, key: str, allowed: dict[str, str], required: tuple[str, ...] = ()) -> dict:
        if not isinstance(value, dict):
            self.fail(key, f"expected a mapping, got {type(value).__name__}", sorted(allowed))
        for k in value:
            if k not in allowed:
                self.fail(f"{key}.{k}" if key else str(k), "unknown key", sorted(allowed))
        for k in required:
            if k not in value:
                self.fail(f"{key}.{k}" if key else k, "missing required key", sorted(allowed))
        return value

    def number(
        self,
        value: Any,
        key: str,
        lo: float | None = None,
        hi: float | None = None,
        unit: str = "",
        lo_open: bool = False,
    ) -> float:
        rng = f"[{lo}, {hi}]{' ' + unit if unit else ''}"
        if lo_open:
            rng = f"({lo}, {hi}]{' ' + unit if unit else ''}"
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.fail(key, f"expected a number, got {value!r}", rng)
        v = float(value)
        if not math.isfinite(v):
            self.fail(key, f"{v} is not finite", rng)
        if lo is not None and (v < lo or (lo_open and v == lo)):
            self.fail(key, f"{v} out of its physical range", rng)
        if hi is not None and v > hi:
            self.fail(key, f"{v} out of its physical range", rng)
        return v

    def integer(self, value: Any, key: str, lo: int, hi: int) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            self.fail(key, f"expected an integer, got {value!r}", f"[{lo}, {hi}]")
        if not lo <= value <= hi:
            self.fail(key, f"{value} out of range", f"[{lo}, {hi}]")
        return int(value)

    def vector(
        self, value: Any, key: str, n: int, lo: float | None = None, hi: float | None = None, unit: str = ""
    ) -> np.ndarray:
        if not isinstance(value, (list, tuple)) or len(value) != n:
            self.fail(
                key,
                f"expected a list of {n} numbers, got {value!r}",
                f"{n} numbers in [{lo}, {hi}]{' ' + unit if unit else ''}",
            )
        return np.array([self.number(v, f"{key}[{i}]", lo, hi, unit) for i, v in enumerate(value)])

    def string(self, value: Any, key: str, choices: tuple | None = None) -> str:
        if not isinstance(value, str) or (choices is not None and value not in choices):
            self.fail(key, f"invalid value {value!r}", list(choices) if choices else "a string")
        return value


def look_at(position: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0), roll_rad: float = 0.0) -> np.ndarray:
    """Camera-to-world transform of an OpenCV optical frame (z forward, x right, y down)."""
    z = np.asarray(target, float) - np.asarray(position, float)
    z /= np.linalg.norm(z)
    up = np.asarray(up, float)
    y = -(up - np.dot(up, z) * z)
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    if roll_rad:
        c, s = math.cos(roll_rad), math.sin(roll_rad)
        x, y = c * x + s * y, -s * x + c * y
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = position
    return T


# --------------------------------------------------------------------------------------
# load_scene
# --------------------------------------------------------------------------------------

_TOP_KEYS = {
    "name": "scene name",
    "seed": "default random seed",
    "workspace": "box the objects and the TCP stay in",
    "table": "the table",
    "objects": "objects on the table",
    "cameras": "depth cameras",
    "gripper": "gripper geometry",
    "gelsight": "GelSight sensors",
    "effects": "effects to simulate",
}


def resolve_path(path: str | os.PathLike) -> Path:
    """A path as written in a scene or config: absolute, or relative to the repository root
    (falling back to the current directory)."""
    p = Path(path)
    if p.is_absolute():
        return p
    if (REPO_ROOT / p).exists():
        return REPO_ROOT / p
    return p.resolve()


def load_scene(path: str | os.PathLike) -> Scene:
    """Read and validate a scene file's workcell (no mesh loading: the simulator checks the
    meshes, the objects' placement and the cameras' view when it builds the world)."""
    file_path = resolve_path(path)
    file = str(path)
    if not file_path.is_file():
        raise SceneError(file, "<file>", "scene file not found", "an existing .yaml file")
    try:
        data = yaml.safe_load(file_path.read_text())
    except yaml.YAMLError as exc:
        raise SceneError(file, "<file>", f"not valid YAML: {exc}", "YAML") from None
    scene = parse_scene(data, file)
    scene.path = str(file_path)
    return scene


def parse_scene(data: Any, file: str = "<scene>") -> Scene:
    """Validate the YAML content of a scene (no mesh loading)."""
    r = SceneReader(file)
    if data is None:
        data = {}
    r.mapping(data, "", _TOP_KEYS, required=("workspace", "objects", "cameras"))
    name = r.string(data.get("name", Path(file).stem), "name")
    seed = r.integer(data.get("seed", 0), "seed", 0, 2**32 - 1)

    ws = r.mapping(data["workspace"], "workspace", {"min_m": "", "max_m": ""}, required=("min_m", "max_m"))
    ws_min = r.vector(ws["min_m"], "workspace.min_m", 3, -5.0, 5.0, "m")
    ws_max = r.vector(ws["max_m"], "workspace.max_m", 3, -5.0, 5.0, "m")
    if np.any(ws_max <= ws_min):
        r.fail("workspace.max_m", f"must exceed workspace.min_m {ws_min.tolist()} on every axis", "max > min per axis")

    table = TableSpec()
    if "table" in data:
        t = r.mapping(data["table"], "table", {"size_m": "", "center_m": "", "thickness_m": ""})
        if "size_m" in t:
            table.size_m = tuple(r.vector(t["size_m"], "table.size_m", 2, 0.1, 10.0, "m"))
        if "center_m" in t:
            table.center_m = tuple(r.vector(t["center_m"], "table.center_m", 2, -5.0, 5.0, "m"))
        if "thickness_m" in t:
            table.thickness_m = r.number(t["thickness_m"], "table.thickness_m", 0.005, 0.5, "m")

    objects = _parse_objects(r, data["objects"])
    cameras = _parse_cameras(r, data["cameras"])
    gripper, gelsight = _parse_gripper(r, data.get("gripper", {}), data.get("gelsight", {}))
    effects = _parse_effects(r, data.get("effects", []) or [], [c.name for c in cameras])
    # An object's relief is simulated only when the scene lists micro_relief: without it the
    # geometry is the exact mesh.
    return Scene(
        path=file,
        name=name,
        workspace_min_m=ws_min,
        workspace_max_m=ws_max,
        table=table,
        objects=objects,
        cameras=cameras,
        gripper=gripper,
        gelsight=gelsight,
        effects=effects,
        seed=seed,
    )


_OBJECT_KEYS = {"name": "", "mesh": "", "primitive": "", "pose": "", "relief": ""}
_POSE_KEYS = {"x_m": "", "y_m": "", "z_m": "", "yaw_deg": ""}
_RELIEF_KEYS = {"kind": "", "pitch_mm": "", "depth_mm": "", "axis": "", "angle_deg": ""}


def _parse_objects(r: SceneReader, value: Any) -> list[ObjectSpec]:
    if not isinstance(value, list):
        r.fail("objects", "expected a list of objects", "list of {name, mesh|primitive, pose, relief}")
    objects, names = [], set()
    for i, item in enumerate(value):
        key = f"objects[{i}]"
        o = r.mapping(item, key, _OBJECT_KEYS, required=("name", "pose"))
        name = r.string(o["name"], f"{key}.name")
        if name in names:
            r.fail(f"{key}.name", f"duplicate object name {name!r}", "unique names")
        names.add(name)
        if ("mesh" in o) == ("primitive" in o):
            r.fail(key, "give exactly one of mesh or primitive", ["mesh", "primitive"])
        mesh = primitive = None
        if "mesh" in o:
            mesh = r.string(o["mesh"], f"{key}.mesh")
            if not resolve_path(mesh).is_file():
                r.fail(
                    f"{key}.mesh",
                    f"mesh file {mesh!r} not found",
                    "a mesh path relative to the repository, e.g. assets/ycb/MustardBottle.obj",
                )
        else:
            primitive = _parse_primitive(r, o["primitive"], f"{key}.primitive")
        pose = r.mapping(o["pose"], f"{key}.pose", _POSE_KEYS, required=("x_m", "y_m"))
        x = r.number(pose["x_m"], f"{key}.pose.x_m", -5.0, 5.0, "m")
        y = r.number(pose["y_m"], f"{key}.pose.y_m", -5.0, 5.0, "m")
        z = r.number(pose["z_m"], f"{key}.pose.z_m", -1.0, 5.0, "m") if "z_m" in pose else None
        yaw = math.radians(r.number(pose.get("yaw_deg", 0.0), f"{key}.pose.yaw_deg", -360.0, 360.0, "deg"))
        relief = _parse_relief(r, o.get("relief", []) or [], f"{key}.relief")
        objects.append(ObjectSpec(name, mesh, primitive, x, y, yaw, z, relief))
    return objects


def _parse_primitive(r: SceneReader, value: Any, key: str) -> dict[str, Any]:
    """An object's primitive shape: exactly one of box, cylinder or sphere, sizes in metres."""
    p = r.mapping(value, key, {"box": "", "cylinder": "", "sphere": ""})
    if len(p) != 1:
        r.fail(key, "give exactly one primitive", ["box", "cylinder", "sphere"])
    kind = next(iter(p))
    if kind == "box":
        return {"box": r.vector(p["box"], f"{key}.box", 3, 0.002, 1.0, "m").tolist()}
    if kind == "cylinder":
        return {"cylinder": r.vector(p["cylinder"], f"{key}.cylinder", 2, 0.001, 1.0, "m").tolist()}
    return {"sphere": r.number(p["sphere"], f"{key}.sphere", 0.001, 1.0, "m")}


def _parse_relief(r: SceneReader, value: Any, key: str) -> list[ReliefSpec]:
    """An object's micro-relief: a list of ridges, knurling or bumps, each shallower than its pitch."""
    if not isinstance(value, list):
        r.fail(key, "expected a list", "list of {kind, pitch_mm, depth_mm, axis, angle_deg}")
    relief = []
    for j, ritem in enumerate(value):
        rkey = f"{key}[{j}]"
        rr = r.mapping(ritem, rkey, _RELIEF_KEYS, required=("kind", "pitch_mm", "depth_mm"))
        kind = r.string(rr["kind"], f"{rkey}.kind", RELIEF_KINDS)
        pitch = r.number(rr["pitch_mm"], f"{rkey}.pitch_mm", 0.2, 50.0, "mm")
        depth = r.number(rr["depth_mm"], f"{rkey}.depth_mm", 0.005, 3.0, "mm")
        if depth > pitch:
            r.fail(f"{rkey}.depth_mm", f"depth {depth} mm exceeds the pitch {pitch} mm", f"(0.005, {pitch}] mm")
        axis = (0.0, 0.0, 1.0)
        if "axis" in rr:
            a = r.vector(rr["axis"], f"{rkey}.axis", 3, -1.0, 1.0)
            if np.linalg.norm(a) < 1e-6:
                r.fail(f"{rkey}.axis", "zero vector", "a non-zero direction in the object frame")
            axis = tuple((a / np.linalg.norm(a)).tolist())
        angle = r.number(rr.get("angle_deg", 30.0), f"{rkey}.angle_deg", 5.0, 85.0, "deg")
        relief.append(ReliefSpec(kind, pitch, depth, axis, angle))
    return relief


_CAMERA_KEYS = {"name": "", "intrinsics": "", "pose": ""}
_INTR_KEYS = {"width": "", "height": "", "fx": "", "fy": "", "cx": "", "cy": ""}
_CAM_POSE_KEYS = {"position_m": "", "look_at_m": "", "roll_deg": ""}


def _parse_cameras(r: SceneReader, value: Any) -> list[CameraSpec]:
    if not isinstance(value, list) or not value:
        r.fail("cameras", "expected a non-empty list of cameras", "list of {name, intrinsics, pose}")
    cams, names = [], set()
    for i, item in enumerate(value):
        key = f"cameras[{i}]"
        c = r.mapping(item, key, _CAMERA_KEYS, required=("name", "pose"))
        name = r.string(c["name"], f"{key}.name")
        if name in names or not name.isidentifier():
            r.fail(f"{key}.name", f"invalid or duplicate camera name {name!r}", "unique identifiers")
        names.add(name)
        intr = r.mapping(c.get("intrinsics", {}), f"{key}.intrinsics", _INTR_KEYS)
        width = r.integer(intr.get("width", 512), f"{key}.intrinsics.width", 8, 4096)
        height = r.integer(intr.get("height", 424), f"{key}.intrinsics.height", 8, 4096)
        fx = r.number(intr.get("fx", 365.5), f"{key}.intrinsics.fx", 10.0, 10000.0, "px")
        fy = r.number(intr.get("fy", 365.5), f"{key}.intrinsics.fy", 10.0, 10000.0, "px")
        cx = r.number(intr.get("cx", 254.9), f"{key}.intrinsics.cx", 0.0, float(width), "px")
        cy = r.number(intr.get("cy", 205.4), f"{key}.intrinsics.cy", 0.0, float(height), "px")
        pose = r.mapping(c["pose"], f"{key}.pose", _CAM_POSE_KEYS, required=("position_m", "look_at_m"))
        pos = r.vector(pose["position_m"], f"{key}.pose.position_m", 3, -10.0, 10.0, "m")
        tgt = r.vector(pose["look_at_m"], f"{key}.pose.look_at_m", 3, -10.0, 10.0, "m")
        roll = math.radians(r.number(pose.get("roll_deg", 0.0), f"{key}.pose.roll_deg", -180.0, 180.0, "deg"))
        d = tgt - pos
        if np.linalg.norm(d) < 1e-3:
            r.fail(f"{key}.pose.look_at_m", "coincides with position_m", "a point away from the camera")
        up = (0.0, 0.0, 1.0)
        if np.linalg.norm(np.cross(d / np.linalg.norm(d), up)) < 1e-3:
            up = (0.0, 1.0, 0.0)  # looking straight down/up: image "up" is world +y
        cams.append(CameraSpec(name, width, height, fx, fy, cx, cy, look_at(pos, tgt, up=up, roll_rad=roll)))
    return cams


_GRIPPER_KEYS = {
    "tcp_to_gel_centre_m": "",
    "max_width_m": "",
    "gel_size_mm": "",
    "elastomer_thickness_mm": "",
    "gel_youngs_modulus_mpa": "",
    "grasp_force_n": "",
}
_GELSIGHT_KEYS = {"image_height": "", "image_width": "", "mm_per_px": "", "calibration_dir": ""}


def _parse_gripper(r: SceneReader, g: Any, s: Any) -> tuple[GripperSpec, GelSightSpec]:
    g = r.mapping(g or {}, "gripper", _GRIPPER_KEYS)
    spec = GripperSpec()
    if "tcp_to_gel_centre_m" in g:
        spec.tcp_to_gel_centre_m = r.number(g["tcp_to_gel_centre_m"], "gripper.tcp_to_gel_centre_m", 0.0, 0.5, "m")
    if "max_width_m" in g:
        spec.max_width_m = r.number(g["max_width_m"], "gripper.max_width_m", 0.01, 0.3, "m")
    if "gel_size_mm" in g:
        spec.gel_size_m = tuple(
            (r.vector(g["gel_size_mm"], "gripper.gel_size_mm", 2, 2.0, 100.0, "mm") * 1e-3).tolist()
        )
    if "elastomer_thickness_mm" in g:
        spec.elastomer_thickness_m = (
            r.number(g["elastomer_thickness_mm"], "gripper.elastomer_thickness_mm", 0.2, 10.0, "mm") * 1e-3
        )
    if "gel_youngs_modulus_mpa" in g:
        spec.gel_youngs_modulus_mpa = r.number(
            g["gel_youngs_modulus_mpa"], "gripper.gel_youngs_modulus_mpa", 0.01, 10.0, "MPa"
        )
    if "grasp_force_n" in g:
        spec.grasp_force_n = r.number(g["grasp_force_n"], "gripper.grasp_force_n", 0.5, 200.0, "N")
    s = r.mapping(s or {}, "gelsight", _GELSIGHT_KEYS)
    gs = GelSightSpec()
    if "image_height" in s:
        gs.image_height = r.integer(s["image_height"], "gelsight.image_height", 8, 2048)
    if "image_width" in s:
        gs.image_width = r.integer(s["image_width"], "gelsight.image_width", 8, 2048)
    if "mm_per_px" in s:
        gs.mm_per_px = r.number(s["mm_per_px"], "gelsight.mm_per_px", 0.005, 1.0, "mm/px")
    if "calibration_dir" in s:
        if not isinstance(s["calibration_dir"], str) or not s["calibration_dir"]:
            r.fail("gelsight.calibration_dir", f"expected a directory, got {s['calibration_dir']!r}", "a path")
        gs.calibration_dir = s["calibration_dir"]
    return spec, gs


def _parse_effects(r: SceneReader, value: Any, camera_names: list[str]) -> list[EffectSpec]:
    """The effects as listed: each a name, or a mapping with a name, an optional ``camera`` of
    this scene and its parameters (checked by the simulator's registry, ``sim.effects``)."""
    if not isinstance(value, list):
        r.fail("effects", "expected a list of effects", "list of names or {name, parameters}")
    out: list[EffectSpec] = []
    seen: set[tuple[str, str | None]] = set()
    for i, item in enumerate(value):
        key = f"effects[{i}]"
        if isinstance(item, str):
            item = {"name": item}
        if not isinstance(item, dict) or not isinstance(item.get("name"), str):
            r.fail(key, "expected an effect name or a mapping with a name", "see scenes/README.md")
        name = item["name"]
        camera = None
        if "camera" in item:
            camera = r.string(item["camera"], f"{key}.camera", tuple(camera_names))
        if (name, camera) in seen or (name, None) in seen or (camera is None and any(n == name for n, _ in seen)):
            r.fail(key, f"effect {name!r} listed twice for the same camera", "each effect once per target")
        seen.add((name, camera))
        params = {k: v for k, v in item.items() if k not in ("name", "camera")}
        out.append(EffectSpec(name, params, camera, key))
    return out
