"""The simulated world: objects on a table, seen by depth cameras and touched by the gels.

:class:`SimWorld` builds, from a validated :class:`workcell.scene.Scene`, an Open3D
``RaycastingScene`` of the table and the objects (meshes in metres, placed in ``world``),
and answers two questions:

- :meth:`SimWorld.render_depth` — the z-depth image (float32 metres, NaN = no return) a
  camera sees, exact geometry when the scene calls for no effect, else with the scene's
  depth effects (``sim/depth_effects.py``) and object micro-relief.
- :meth:`SimWorld.grasp_contact` — where the two gels of a top-down grasp touch the object,
  how deep they press at a given force, and the per-pixel gel gap maps (mm in the gel frame)
  the GelSight renderer turns into images.

Gap maps: pixel (row r, column c) of an H x W map covering ``extent_mm = (ez, ex)`` is the
point ``z = (r - (H-1)/2) * ez/H``, ``x = (c - (W-1)/2) * ex/W`` of the gel plane (gel frame
of ``workcell.kinematics.gel_poses_world``; rows run along gel z = the finger axis toward
the fingertip, columns along gel x, the same orientation as the depth-maps of
``perception.depthmap``). The value is the y of the object surface there (mm; > 0 free,
< 0 pressing into the gel, +inf nothing there).

Gel compliance: the elastomer is a Winkler (mattress) layer, every point pushing back with a
pressure proportional to its own compression: p = k * delta with k = E / t (gel Young's
modulus over elastomer thickness; scene defaults 0.25 MPa / 2 mm = 0.125 N/mm of indentation
per mm^2 of contact area). The object approaches the gel rigidly by d until
``F = k * sum(max(0, d - gap_i)) * cell_area`` over a 0.3 mm grid of the gel area; d is
capped at the elastomer thickness (``saturated``). A flat face of the whole 18.6 x 24.9 mm
gel at 10 N gives d = 0.17 mm; a 30 mm radius cylinder about 0.46 mm. The lateral spread of
the gel around the contact is the GelSight renderer's business (``sim.gelsight``).

Depth frames: the world is static (objects do not move and the robot is not drawn), so
each camera's exact ray cast is done once and cached; a frame then costs its effects only.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from pathlib import Path

import numpy as np
import open3d as o3d
import open3d.core as o3c
from scipy import ndimage

from sim.depth_effects import DepthEffectChain, gaussian
from sim.effects import DEPTH_EFFECT_ORDER, resolve_effects
from sim.seeding import state_rng
from workcell.kinematics import gel_poses_world
from workcell.parts import ObjectSpec, ReliefSpec
from workcell.scene import Scene, SceneError, load_scene, resolve_path

# How far behind the gel plane gap-map rays start (mm): surfaces up to this deep in the gel
# are still measured.
_BACK_OFF_MM = 5.0
# Grid spacing (mm) over the gel area used to find the first touch and the force balance.
_CONTACT_GRID_MM = 0.3


# --------------------------------------------------------------------------------------
# Meshes
# --------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=32)
def _load_mesh_file(path: str) -> tuple[np.ndarray, np.ndarray, str]:
    """(vertices float64 Nx3, triangles int32 Mx3, problem) of a mesh file, duplicates merged.
    ``problem`` is empty for a usable mesh, else says what is wrong."""
    raw = o3d.io.read_triangle_mesh(path)
    verts = np.asarray(raw.vertices, dtype=np.float64)
    tris = np.asarray(raw.triangles, dtype=np.int32)
    if len(verts) == 0 or len(tris) == 0:
        return verts, tris, "empty mesh (no vertices or no triangles)"
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tris))
    mesh.remove_duplicated_vertices()
    mesh.remove_degenerate_triangles()
    mesh.remove_unreferenced_vertices()
    if len(mesh.triangles) == 0:
        return verts, tris, "empty mesh (only degenerate triangles)"
    if not mesh.is_edge_manifold(allow_boundary_edges=True):
        return verts, tris, "non-manifold mesh (an edge is shared by more than two triangles)"
    if not mesh.is_vertex_manifold():
        return verts, tris, "non-manifold mesh (a vertex's faces do not form a single fan)"
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int32), ""


def _primitive_mesh(primitive: dict) -> tuple[np.ndarray, np.ndarray]:
    kind, value = next(iter(primitive.items()))
    if kind == "box":
        sx, sy, sz = value
        mesh = o3d.geometry.TriangleMesh.create_box(sx, sy, sz)
        mesh.translate((-sx / 2, -sy / 2, -sz / 2))
    elif kind == "cylinder":
        radius, height = value
        mesh = o3d.geometry.TriangleMesh.create_cylinder(radius, height, resolution=256, split=1)
    else:
        mesh = o3d.geometry.TriangleMesh.create_sphere(float(value), resolution=200)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int32)


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------------------
# Micro-relief
# --------------------------------------------------------------------------------------


def _perpendicular(a: np.ndarray) -> np.ndarray:
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e = np.cross(a, helper)
    return e / np.linalg.norm(e)


def relief_height_mm(relief: list[ReliefSpec], p_obj_m: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Outward displacement (mm, >= 0) of the surface at points ``p_obj_m`` (N x 3, object
    frame, metres) for a list of relief patterns (summed)."""
    p = np.asarray(p_obj_m, dtype=np.float64) * 1e3
    h = np.zeros(len(p), dtype=np.float64)
    for r in relief:
        a = np.asarray(r.axis, dtype=np.float64)
        two_pi = 2.0 * math.pi / r.pitch_mm
        if r.kind == "ridges":
            h += r.depth_mm * 0.5 * (1.0 - np.cos(two_pi * (p @ a)))
        elif r.kind == "knurling":
            e = _perpendicular(a)
            t = math.radians(r.angle_deg)
            d1 = math.cos(t) * a + math.sin(t) * e
            d2 = math.cos(t) * a - math.sin(t) * e
            h += r.depth_mm * 0.25 * ((1.0 - np.cos(two_pi * (p @ d1))) + (1.0 - np.cos(two_pi * (p @ d2))))
        else:  # bumps: spherical-cap-like bumps on a cubic lattice
            q = p / r.pitch_mm
            f = (q - np.round(q)) * r.pitch_mm
            dist2 = np.einsum("ij,ij->i", f, f)
            radius2 = (0.4 * r.pitch_mm) ** 2
            h += r.depth_mm * np.sqrt(np.clip(1.0 - dist2 / radius2, 0.0, None))
    return h * scale


# --------------------------------------------------------------------------------------
# Contact results
# --------------------------------------------------------------------------------------


@dataclasses.dataclass
class FingerContact:
    """One finger of a grasp. ``gel_to_world`` is the gel frame where the finger stopped."""

    finger: str
    gel_to_world: np.ndarray  # where the gel (its rigid backing) ends, pressed at the force
    in_contact: bool
    travel_m: float  # how far the gel moved from the open position (first touch + press)
    indentation_mm: float  # press after the first touch: the object's approach into the gel
    contact_area_mm2: float
    saturated: bool = False  # force needs more than the elastomer thickness of indentation
    collision: bool = False  # the open finger already intersected an object


@dataclasses.dataclass
class GraspContact:
    """Result of :meth:`SimWorld.grasp_contact`. ``gap_mm[finger]`` is the gel gap map at
    the requested size (mm; negative = pressing into the gel; +inf = nothing)."""

    tcp_pose_world: np.ndarray
    force_n: float
    width_m: float
    fingers: dict[str, FingerContact]
    gap_mm: dict[str, np.ndarray]
    world: "SimWorld" = dataclasses.field(repr=False, default=None)
    # Each finger closes to its own contact, as if the object slid to sit between the fingers;
    # the midpoint of the two gels ends this far from the TCP along tool +y (0 when centred).
    centre_shift_m: float = 0.0

    def gap_map(self, finger: str, size: tuple[int, int], extent_mm: tuple[float, float] | None = None) -> np.ndarray:
        """The gap map of ``finger`` at another size (same contact)."""
        fc = self.fingers[finger]
        return self.world.gap_map(fc.gel_to_world, size, extent_mm)


@dataclasses.dataclass
class _Camera:
    spec: object
    nominal_to_world: np.ndarray
    true_to_world: np.ndarray
    effects: DepthEffectChain
    u: np.ndarray  # H*W float32 pixel columns
    v: np.ndarray
    dirs_cam: np.ndarray  # H*W x 3 float32, z component 1
    rays: o3c.Tensor  # H*W x 6 float32 (true pose)
    dirs_world: np.ndarray
    stream: int  # the camera's noise stream (its index in the scene)
    cache: tuple | None = None  # exact (z, cos incidence), flat
    recast_idx: np.ndarray | None = None
    smooth_idx: np.ndarray | None = None
    inv_z_smooth: np.ndarray | None = None
    lateral_scale_smooth: np.ndarray | None = None
    static: dict | None = None  # per-pixel quantities of the exact cast the effects reuse


# --------------------------------------------------------------------------------------
# The world
# --------------------------------------------------------------------------------------


class SimWorld:
    """Ray-cast world of one scene. ``seed`` (default: the scene's) seeds every effect's
    draws (``sim.seeding``); two worlds with the same scene and seed produce identical frames."""

    def __init__(self, scene: Scene, seed: int | None = None, check: bool = False, file_label: str | None = None):
        scene = resolve_effects(scene)
        self.scene = scene
        self.seed = scene.seed if seed is None else int(seed)
        label = file_label or scene.path
        relief_effect = scene.effect("micro_relief")
        self.relief_scale = float(relief_effect.params["scale"]) if relief_effect else 0.0

        self.object_to_world: list[np.ndarray] = []
        self.object_meshes: list[tuple[np.ndarray, np.ndarray]] = []  # world-frame vertices, triangles
        self.object_aabbs: list[tuple[np.ndarray, np.ndarray]] = []  # world-frame bounds
        for i, obj in enumerate(scene.objects):
            verts, tris = self._object_mesh(obj, i, label)
            R = _rot_z(obj.yaw_rad)
            z = obj.z_m if obj.z_m is not None else -float(verts[:, 2].min())
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = (obj.x_m, obj.y_m, z)
            world_verts = verts @ R.T + T[:3, 3]
            lo, hi = world_verts.min(0), world_verts.max(0)
            if check and (np.any(lo < scene.workspace_min_m - 1e-6) or np.any(hi > scene.workspace_max_m + 1e-6)):
                raise SceneError(
                    label,
                    f"objects[{i}].pose",
                    f"object {obj.name!r} spans {lo.round(3).tolist()}..{hi.round(3).tolist()} m, "
                    "outside the workspace",
                    f"workspace min_m {scene.workspace_min_m.tolist()} .. max_m {scene.workspace_max_m.tolist()}",
                )
            self.object_to_world.append(T)
            self.object_meshes.append((world_verts, tris))
            self.object_aabbs.append((lo, hi))

        # Camera scene: table (geometry id 0) then objects (1..n). Contact scene: objects only.
        self._scene = o3d.t.geometry.RaycastingScene()
        self._contact_scene = o3d.t.geometry.RaycastingScene()
        tv, tt = self._table_mesh()
        self._table_id = self._scene.add_triangles(o3c.Tensor(tv.astype(np.float32)), o3c.Tensor(tt.astype(np.uint32)))
        self._camera_geom_to_object: dict[int, int] = {}
        self._contact_geom_to_object: dict[int, int] = {}
        for i, (v, t) in enumerate(self.object_meshes):
            vt, tt_ = o3c.Tensor(v.astype(np.float32)), o3c.Tensor(t.astype(np.uint32))
            self._camera_geom_to_object[self._scene.add_triangles(vt, tt_)] = i
            self._contact_geom_to_object[self._contact_scene.add_triangles(vt, tt_)] = i
        self._relief_objects = [i for i, o in enumerate(scene.objects) if o.relief and self.relief_scale > 0]
        # Sphere primitives are ray-cast on their tessellation, then the hit is moved onto the
        # analytic sphere (float precision instead of the tessellation's chord error).
        self._spheres = {
            i: (self.object_to_world[i][:3, 3].copy(), float(o.primitive["sphere"]))
            for i, o in enumerate(scene.objects)
            if o.primitive and "sphere" in o.primitive
        }

        self.cameras: dict[str, _Camera] = {}
        for ci, cam in enumerate(scene.cameras):
            self.cameras[cam.name] = self._make_camera(cam, ci)
        if check:
            for ci, cam in enumerate(scene.cameras):
                self._check_camera_sees_workspace(cam, ci, label)

    @classmethod
    def from_file(cls, path: str | os.PathLike, seed: int | None = None) -> SimWorld:
        """The world of a scene file, checked completely: the workcell (workcell.scene), the
        effects (sim.effects), the meshes (non-empty, manifold), every object inside the
        workspace and every camera seeing part of it. Each problem is a SceneError."""
        return cls(load_scene(path), seed=seed, check=True, file_label=str(path))

    # ---------------------------------------------------------------- construction
    def _object_mesh(self, obj: ObjectSpec, i: int, label: str) -> tuple[np.ndarray, np.ndarray]:
        if obj.primitive is not None:
            return _primitive_mesh(obj.primitive)
        path = resolve_path(obj.mesh)
        if not Path(path).is_file():
            raise SceneError(
                label,
                f"objects[{i}].mesh",
                f"mesh file {obj.mesh!r} not found",
                "a mesh path relative to the repository, e.g. assets/ycb/MustardBottle.obj",
            )
        verts, tris, problem = _load_mesh_file(str(path))
        if problem:
            raise SceneError(
                label,
                f"objects[{i}].mesh",
                f"{obj.mesh}: {problem}",
                "a non-empty, edge- and vertex-manifold triangle mesh (OBJ/PLY/STL, metres)",
            )
        return verts, tris

    def _table_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        t = self.scene.table
        sx, sy = t.size_m
        box = o3d.geometry.TriangleMesh.create_box(sx, sy, t.thickness_m)
        box.translate((t.center_m[0] - sx / 2, t.center_m[1] - sy / 2, -t.thickness_m))
        return np.asarray(box.vertices), np.asarray(box.triangles, dtype=np.int32)

    def _make_camera(self, cam, index: int) -> _Camera:
        specs = [self.scene.effect(name, cam.name) for name in DEPTH_EFFECT_ORDER]
        chain = DepthEffectChain([s for s in specs if s is not None])
        nominal = cam.camera_to_world.copy()
        true = nominal @ chain.extrinsic.offset_matrix() if chain.extrinsic else nominal
        vv, uu = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float32)
        u, v = uu.reshape(-1), vv.reshape(-1)
        dirs_cam = self._pixel_dirs(cam, u, v)
        dirs_world, rays = self._rays(true, dirs_cam)
        return _Camera(cam, nominal, true, chain, u, v, dirs_cam, rays, dirs_world, index)

    @staticmethod
    def _pixel_dirs(cam, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        d = np.empty((u.size, 3), dtype=np.float32)
        d[:, 0] = (u - np.float32(cam.cx)) / np.float32(cam.fx)
        d[:, 1] = (v - np.float32(cam.cy)) / np.float32(cam.fy)
        d[:, 2] = 1.0
        return d

    @staticmethod
    def _rays(camera_to_world: np.ndarray, dirs_cam: np.ndarray) -> tuple[np.ndarray, o3c.Tensor]:
        R = camera_to_world[:3, :3].astype(np.float32)
        dirs_world = np.einsum("ij,kj->ik", dirs_cam, R)
        rays = np.empty((dirs_cam.shape[0], 6), dtype=np.float32)
        rays[:, :3] = camera_to_world[:3, 3].astype(np.float32)
        rays[:, 3:] = dirs_world
        return dirs_world, o3c.Tensor(rays)

    def _check_camera_sees_workspace(self, cam, index: int, label: str) -> None:
        c = self.cameras[cam.name]
        step = 8
        sel = (c.u.astype(int) % step == 0) & (c.v.astype(int) % step == 0)
        rays = c.rays.numpy()[sel]
        ans = self._scene.cast_rays(o3c.Tensor(np.ascontiguousarray(rays)))
        t = ans["t_hit"].numpy()
        hit = np.isfinite(t)
        pts = rays[hit, :3] + t[hit, None] * rays[hit, 3:]
        lo = self.scene.workspace_min_m - 0.01
        hi = self.scene.workspace_max_m + 0.01
        inside = np.all((pts >= lo) & (pts <= hi), axis=1)
        if not np.any(inside):
            raise SceneError(
                label,
                f"cameras[{index}].pose",
                f"camera {cam.name!r} sees nothing of the workspace",
                "a pose whose view contains part of the workspace box "
                f"{self.scene.workspace_min_m.tolist()}..{self.scene.workspace_max_m.tolist()} m",
            )

    # ---------------------------------------------------------------- depth
    def camera_names(self) -> list[str]:
        return list(self.cameras)

    def nominal_camera_to_world(self, camera: str) -> np.ndarray:
        """The extrinsic the driver reports (the calibration offset effect is hidden in it)."""
        return self.cameras[camera].nominal_to_world.copy()

    def true_camera_to_world(self, camera: str) -> np.ndarray:
        return self.cameras[camera].true_to_world.copy()

    def render_depth(self, camera: str, rng: np.random.Generator | None = None) -> np.ndarray:
        """z-depth image (H x W float32 metres along the optical axis, NaN where no return)
        of ``camera``; effects draw from ``rng`` (default: keyed on the world's seed and the
        camera, ``sim.seeding``: the world is static, so every frame shows the same state and
        carries the same noise, whichever frame a node takes).

        The exact ray cast of each camera (true pose, micro-relief included) is done once and
        cached; each frame then costs only its effects."""
        c = self.cameras[camera]
        rng = state_rng(b"static world", self.seed, c.stream) if rng is None else rng
        cam = c.spec
        chain = c.effects
        if c.cache is None:
            self._build_cache(c)
        z, cos_inc = c.cache
        if chain.lateral is not None:
            z, cos_inc = self._lateral(c, rng)
        else:
            z = z.copy()
        z = z.reshape(cam.height, cam.width)
        if cos_inc is not None:
            cos_inc = cos_inc.reshape(cam.height, cam.width)
        return chain.measure(z, cos_inc, rng, c.static, c.recast_idx if chain.lateral is not None else None)

    def _cast_camera(
        self, c: "_Camera", rays: o3c.Tensor, dirs_world: np.ndarray, nthreads: int = 0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Exact cast: (z-depth float32 with NaN, cos incidence float32 or None, geometry ids)."""
        ans = self._scene.cast_rays(rays, nthreads=nthreads)
        # Ray directions have a camera-frame z component of exactly 1, so the hit parameter
        # is the z-depth itself (not the ray length).
        z = ans["t_hit"].numpy()
        gids = ans["geometry_ids"].numpy()
        cos_inc = None
        need_normals = c.effects.needs_incidence or bool(self._relief_objects)
        n = ans["primitive_normals"].numpy() if need_normals else None
        if self._spheres:
            z = z.copy()
            n = None if n is None else n.copy()
            self._refine_spheres(rays.numpy(), z, gids, n, self._camera_geom_to_object)
        if need_normals:
            ndotd = np.einsum("ij,ij->i", n, dirs_world)
            dnorm = np.sqrt(np.einsum("ij,ij->i", dirs_world, dirs_world))
            if self._relief_objects:
                z = self._apply_relief_depth(z, gids, rays, ndotd, dnorm)
            if c.effects.needs_incidence:
                cos_inc = (np.abs(ndotd) / dnorm).astype(np.float32)
        z = np.where(np.isfinite(z), z, np.float32(np.nan)).astype(np.float32, copy=False)
        return z, cos_inc, gids

    def _build_cache(self, c: "_Camera") -> None:
        z, cos_inc, gids = self._cast_camera(c, c.rays, c.dirs_world)
        c.cache = (z, cos_inc)
        c.static = c.effects.prepare(
            z.reshape(c.spec.height, c.spec.width),
            None if cos_inc is None else cos_inc.reshape(c.spec.height, c.spec.width),
        )
        if c.effects.lateral is None:
            return
        # Pixels whose jittered ray may land on another surface (depth jump, another
        # geometry, no return) within the jitter radius are re-cast each frame; elsewhere the
        # jittered sample follows from the local inverse-depth gradient (exact on planes).

        h, w = c.spec.height, c.spec.width
        zi = z.reshape(h, w)
        gi = gids.reshape(h, w).astype(np.int64)
        valid = np.isfinite(zi)
        disc = np.zeros((h, w), dtype=bool)
        for axis in (0, 1):
            a = [slice(None)] * 2
            b = [slice(None)] * 2
            a[axis], b[axis] = slice(1, None), slice(None, -1)
            za, zb = zi[tuple(a)], zi[tuple(b)]
            with np.errstate(invalid="ignore"):
                jump = (valid[tuple(a)] != valid[tuple(b)]) | (gi[tuple(a)] != gi[tuple(b)])
                jump |= np.abs(za - zb) > 0.01 * np.fmin(za, zb)
            jump &= valid[tuple(a)] | valid[tuple(b)]
            disc[tuple(a)] |= jump
            disc[tuple(b)] |= jump
        # A jump lies half a pixel beyond a flagged pixel, so a pixel ``radius`` away from
        # every flagged one keeps its jittered sample (|jitter| <= 3 sigma) on its own surface.
        radius = max(1, int(math.ceil(3.0 * c.effects.lateral.sigma_px - 0.5)))
        near = ndimage.binary_dilation(disc, structure=np.ones((3, 3), bool), iterations=radius)
        near &= ndimage.binary_dilation(valid, structure=np.ones((3, 3), bool), iterations=radius)
        c.recast_idx = np.flatnonzero(near)
        c.smooth_idx = np.flatnonzero(valid & ~near)
        inv_z = np.where(valid, 1.0 / np.where(valid, zi, 1.0), 0.0)
        gv, gu = np.gradient(inv_z)  # central differences: exact for 1/z affine (planes)
        c.inv_z_smooth = inv_z.reshape(-1)[c.smooth_idx].astype(np.float32)
        # gu du + gv dv with du, dv ~ N(0, s^2) is N(0, s^2 (gu^2 + gv^2)): one draw per pixel
        grad = np.hypot(gu, gv).reshape(-1)[c.smooth_idx]
        c.lateral_scale_smooth = (grad * c.effects.lateral.sigma_px).astype(np.float32)

    def _lateral(self, c: "_Camera", rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray | None]:
        lat = c.effects.lateral
        cam = c.spec
        z0, cos0 = c.cache
        sigma = np.float32(lat.sigma_px)
        limit = np.float32(3.0 * lat.sigma_px)  # jitter truncated at 3 sigma
        z = np.full(z0.shape, np.nan, dtype=np.float32)
        cos_inc = None if cos0 is None else cos0.copy()
        # smooth pixels: 1/z is affine in (u, v) on a plane, so the jittered sample is
        # 1 / (1/z + d(1/z)/du du + d(1/z)/dv dv) (exact on planes, first order elsewhere)
        idx = c.smooth_idx
        n = np.clip(gaussian(rng, idx.size), -3.0, 3.0)
        z[idx] = 1.0 / (c.inv_z_smooth + c.lateral_scale_smooth * n)
        # pixels near discontinuities: cast the jittered rays exactly
        idx = c.recast_idx
        if idx.size:
            jit = np.clip(gaussian(rng, 2 * idx.size).reshape(2, idx.size) * sigma, -limit, limit)
            dirs_cam = self._pixel_dirs(cam, c.u[idx] + jit[0], c.v[idx] + jit[1])
            dirs_world, rays = self._rays(c.true_to_world, dirs_cam)
            # a few thousand rays: one thread avoids waiting on a busy machine's other cores
            zr, cr, _ = self._cast_camera(c, rays, dirs_world, nthreads=1)
            z[idx] = zr
            if cos_inc is not None:
                cos_inc[idx] = cr
        return z, cos_inc

    def _refine_spheres(
        self,
        rays: np.ndarray,
        t: np.ndarray,
        gids: np.ndarray,
        normals: np.ndarray | None,
        geom_to_object: dict[int, int],
    ) -> None:
        """In place: hits on sphere primitives moved onto the analytic sphere (t, normals)."""
        for gid, oi in geom_to_object.items():
            if oi not in self._spheres:
                continue
            idx = np.flatnonzero(gids == gid)
            if idx.size == 0:
                continue
            centre, radius = self._spheres[oi]
            o = rays[idx, :3].astype(np.float64) - centre
            d = rays[idx, 3:].astype(np.float64)
            a = np.einsum("ij,ij->i", d, d)
            b = np.einsum("ij,ij->i", o, d)
            c = np.einsum("ij,ij->i", o, o) - radius * radius
            disc = b * b - a * c
            ok = disc >= 0  # always, as the tessellation lies inside the sphere
            th = (-b - np.sqrt(np.where(ok, disc, 0.0))) / a
            t[idx[ok]] = th[ok]
            if normals is not None:
                normals[idx[ok]] = ((o + th[:, None] * d) / radius)[ok]

    def _apply_relief_depth(self, t, geom_ids, rays, ndotd, dnorm):
        rays_np = rays.numpy() if isinstance(rays, o3c.Tensor) else rays
        t = t.copy()
        for gid, oi in self._camera_geom_to_object.items():
            if oi not in self._relief_objects:
                continue
            idx = np.flatnonzero(geom_ids == gid)
            if idx.size == 0:
                continue
            r = rays_np[idx]
            p = r[:, :3] + t[idx, None] * r[:, 3:]
            t[idx] = t[idx] + self._relief_dt(oi, p, ndotd[idx], dnorm[idx])
        return t

    def _relief_dt(self, oi: int, p_world: np.ndarray, ndotd: np.ndarray, dnorm: np.ndarray) -> np.ndarray:
        """Change of the ray parameter when the surface is pushed out by the relief: the
        displaced tangent plane n.x = n.p + h is met at t + h / (n.d) (n.d < 0 when facing)."""
        T = self.object_to_world[oi]
        p_obj = (p_world - T[:3, 3]) @ T[:3, :3]
        h_m = relief_height_mm(self.scene.objects[oi].relief, p_obj, self.relief_scale) * 1e-3
        denom = np.minimum(ndotd, -0.1 * dnorm)  # facing side; grazing clamped
        return (h_m / denom).astype(np.float32)

    def point_cloud(self, camera: str, depth: np.ndarray | None = None, nominal: bool = True) -> np.ndarray:
        """Back-project a depth image to world points (N x 3) with the nominal (reported) or
        the true extrinsic."""
        c = self.cameras[camera]
        z = self.render_depth(camera) if depth is None else depth
        zf = z.reshape(-1)
        ok = np.isfinite(zf)
        pts_cam = c.dirs_cam[ok] * zf[ok, None]
        T = c.nominal_to_world if nominal else c.true_to_world
        return pts_cam @ T[:3, :3].T + T[:3, 3]

    # ---------------------------------------------------------------- contact
    def gel_grid(self, size: tuple[int, int], extent_mm: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
        """Gel-frame (x, z) in metres of the pixel centres of an H x W map covering
        ``extent_mm = (along rows = gel z, along columns = gel x)``; both arrays H x W.
        Rows run along gel z and columns along gel x, as in ``perception.depthmap``."""
        h, w = int(size[0]), int(size[1])
        ez, ex = float(extent_mm[0]) * 1e-3, float(extent_mm[1]) * 1e-3
        z = (np.arange(h) - (h - 1) / 2.0) * (ez / h)
        x = (np.arange(w) - (w - 1) / 2.0) * (ex / w)
        zz, xx = np.meshgrid(z, x, indexing="ij")
        return xx, zz

    def default_extent_mm(self) -> tuple[float, float]:
        g = self.scene.gelsight
        return (g.image_height * g.mm_per_px, g.image_width * g.mm_per_px)

    def _cast_from_gel(self, gel_to_world: np.ndarray, x: np.ndarray, z: np.ndarray, back_off_m: float):
        """Cast rays from gel-plane points (y = -back_off) along gel +y; returns
        (t in metres from the start, front-facing mask)."""
        R, o = gel_to_world[:3, :3], gel_to_world[:3, 3]
        pts = o + np.outer(x.reshape(-1), R[:, 0]) + np.outer(z.reshape(-1), R[:, 2]) - back_off_m * R[:, 1]
        d = np.broadcast_to(R[:, 1], pts.shape)
        rays = np.concatenate([pts, d], axis=1).astype(np.float32)
        ans = self._contact_scene.cast_rays(o3c.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float64)
        hit = np.isfinite(t)
        if not np.any(hit):
            return t, hit
        n = ans["primitive_normals"].numpy()
        if self._spheres:
            n = n.copy()
            self._refine_spheres(rays, t, ans["geometry_ids"].numpy(), n, self._contact_geom_to_object)
        ndotd = n @ R[:, 1]
        front = hit & (ndotd < 0)
        if self._relief_objects:
            gids = ans["geometry_ids"].numpy()
            for gid, oi in self._contact_geom_to_object.items():
                if oi not in self._relief_objects:
                    continue
                idx = np.flatnonzero(front & (gids == gid))
                if idx.size:
                    p = rays[idx, :3] + t[idx, None] * rays[idx, 3:]
                    t[idx] += self._relief_dt(oi, p, ndotd[idx], np.ones(idx.size))
        return t, front

    def near_gel(
        self, gel_to_world: np.ndarray, extent_mm: tuple[float, float] | None = None, reach_m: float = 0.01
    ) -> bool:
        """Whether any object's bounding box comes within ``reach_m`` in front of (or up to
        the ray start behind) the gel area: a cheap test before casting a gap map."""
        extent_mm = self.default_extent_mm() if extent_mm is None else extent_mm
        ez, ex = extent_mm[0] * 5e-4, extent_mm[1] * 5e-4
        corners = np.array([[x, y, z] for x in (-ex, ex) for y in (-_BACK_OFF_MM * 1e-3, reach_m) for z in (-ez, ez)])
        pts = corners @ gel_to_world[:3, :3].T + gel_to_world[:3, 3]
        lo, hi = pts.min(0), pts.max(0)
        return any(np.all(hi >= olo) and np.all(lo <= ohi) for olo, ohi in self.object_aabbs)

    def gap_map(
        self,
        gel_to_world: np.ndarray,
        size: tuple[int, int],
        extent_mm: tuple[float, float] | None = None,
        indentation_mm: float = 0.0,
    ) -> np.ndarray:
        """Gel gap map (H x W float32 mm; + free, - pressing, +inf nothing) of a gel at
        ``gel_to_world`` with the object pressed ``indentation_mm`` further in."""
        extent_mm = self.default_extent_mm() if extent_mm is None else extent_mm
        x, z = self.gel_grid(size, extent_mm)
        t, front = self._cast_from_gel(gel_to_world, x, z, _BACK_OFF_MM * 1e-3)
        gap = np.full(t.shape, np.inf)
        gap[front] = t[front] * 1e3 - _BACK_OFF_MM - indentation_mm
        inside = np.isfinite(t) & ~front  # ray started inside an object: deeply pressed
        gap[inside] = -_BACK_OFF_MM - indentation_mm
        return gap.reshape(int(size[0]), int(size[1])).astype(np.float32)

    def solve_indentation(self, gaps_mm: np.ndarray, cell_area_mm2: float, force_n: float) -> tuple[float, float, bool]:
        """Rigid approach d (mm) of the object into a Winkler-foundation gel so that
        ``force = k * cell_area * sum(max(0, d - gap_i))`` with k = E / thickness (N/mm per mm^2
        of contact area, :attr:`GripperSpec.foundation_stiffness_n_per_mm3`). Returns
        (d, contact area mm^2, saturated: d hit the elastomer thickness)."""
        g = np.sort(gaps_mm[np.isfinite(gaps_mm)])
        if g.size == 0 or force_n <= 0:
            return 0.0, 0.0, False
        k = self.scene.gripper.foundation_stiffness_n_per_mm3
        target = force_n / (k * cell_area_mm2)  # sum of local indentations, mm
        m = np.arange(1, g.size + 1)
        d_cand = (target + np.cumsum(g)) / m
        nxt = np.append(g[1:], np.inf)
        first = int(np.argmax(d_cand <= nxt))
        d = float(d_cand[first])
        thickness_mm = self.scene.gripper.elastomer_thickness_m * 1e3
        saturated = d > thickness_mm
        d = min(d, thickness_mm)
        area = float(np.count_nonzero(g < d) * cell_area_mm2)
        return d, area, saturated

    def grasp_contact(
        self,
        tcp_pose_world: np.ndarray,
        force_n: float,
        size: tuple[int, int] | None = None,
        extent_mm: tuple[float, float] | None = None,
        gap_fingers: tuple[str, ...] = ("left", "right"),
    ) -> GraspContact:
        """Close both gels from the open gripper along the tool y axis until each meets the
        object surface (each finger independently; no object reached = it closes to the
        centre), press with ``force_n`` on the gel's compliance (the finger closes further by
        the indentation, so the gap maps are negative where the object presses into the gel
        and ``width_m`` is the final gel-to-gel distance), and return the contact with
        gap maps at ``size`` (default: the GelSight image size) over ``extent_mm`` (default:
        the GelSight image's field of view) for the fingers in ``gap_fingers``."""

        gr = self.scene.gripper
        geometry = self.scene.gripper_geometry()
        open_poses = gel_poses_world(tcp_pose_world, gr.max_width_m, geometry)
        gx, gz = gr.gel_size_m[0] * 1e3, gr.gel_size_m[1] * 1e3
        nx, nz = max(2, int(round(gx / _CONTACT_GRID_MM))), max(2, int(round(gz / _CONTACT_GRID_MM)))
        cell_area = (gx / nx) * (gz / nz)
        x, z = self.gel_grid((nz, nx), (gz, gx))
        max_travel = gr.max_width_m / 2.0
        fingers: dict[str, FingerContact] = {}
        gaps: dict[str, np.ndarray] = {}
        size = (self.scene.gelsight.image_height, self.scene.gelsight.image_width) if size is None else size
        for finger, pose in open_poses.items():
            t, front = self._cast_from_gel(pose, x, z, 0.0)
            collision = bool(np.any(np.isfinite(t) & ~front))
            reach = front & (t <= max_travel)
            if collision or not np.any(reach):
                travel = max_travel if not collision else 0.0
                in_contact, d, area, sat = False, 0.0, 0.0, False
            else:
                travel = float(t[reach].min())
                gap_local = np.where(front, (t - travel) * 1e3, np.inf)
                d, area, sat = self.solve_indentation(gap_local, cell_area, force_n)
                in_contact = True
            # after the first touch the finger keeps closing by d while the gel compresses
            travel = min(travel + d * 1e-3, max_travel) if in_contact else travel
            gel = pose.copy()
            gel[:3, 3] += travel * pose[:3, 1]
            fingers[finger] = FingerContact(finger, gel, in_contact, travel, d, area, sat, collision)
            if finger in gap_fingers:
                gaps[finger] = self.gap_map(gel, size, extent_mm)
        t_left, t_right = fingers["left"].travel_m, fingers["right"].travel_m
        width = max(0.0, gr.max_width_m - t_left - t_right)
        return GraspContact(
            np.asarray(tcp_pose_world, float).copy(),
            float(force_n),
            width,
            fingers,
            gaps,
            self,
            centre_shift_m=0.5 * (t_right - t_left),
        )

    def contact_width_m(self, tcp_pose_world: np.ndarray, force_n: float = 0.0) -> float | None:
        """Gripper width (m) at which closing at ``tcp_pose_world`` holds the object with
        ``force_n`` (the gels compressed by it), or None when neither finger meets anything:
        what the simulated gripper's ``contact_width_m()`` callback needs."""
        contact = self.grasp_contact(tcp_pose_world, force_n, gap_fingers=())
        if not any(f.in_contact for f in contact.fingers.values()):
            return None
        return contact.width_m


# Worlds shared by the simulated backends of one process (same scene file and seed).
_WORLDS: dict[tuple[str, int | None], SimWorld] = {}


def shared_world(scene_path: str, seed: int | None = None) -> SimWorld:
    """The SimWorld of ``scene_path`` (loaded and checked once per process and seed)."""
    key = (str(resolve_path(scene_path)), seed)
    if key not in _WORLDS:
        _WORLDS[key] = SimWorld.from_file(scene_path, seed=seed)
    return _WORLDS[key]
