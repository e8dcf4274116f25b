"""The simulated world's geometry: the table and the objects of a scene as triangle meshes
(metres), placed in ``world``, and the micro-relief that displaces object surfaces.

:class:`SceneObjects` places a scene's objects (mesh files or primitives) and corrects ray hits
on them where a mesh is only an approximation: sphere primitives are ray-cast on their
tessellation and moved onto the analytic sphere, and objects with relief (when the scene calls
for ``micro_relief``) have their surfaces pushed out by :func:`relief_height_mm`. Both the depth
cameras (``sim.depth_render``) and the gels (``sim.grasp_contact``) cast against these meshes.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import open3d as o3d

from workcell.parts import ObjectSpec, ReliefSpec, TableSpec
from workcell.scene import Scene, SceneError, resolve_path

# --------------------------------------------------------------------------------------
# Meshes
# --------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=32)
def _load_mesh_file(path: str) -> tuple[np.ndarray, np.ndarray, str]:
    """(vertices float64 Nx3, triangles int32 Mx3, problem) of a mesh file, duplicates merged.
    ``problem`` is empty for a usable mesh, else says what is wrong."""
    raw = o3d.io.read_triangle_mesh(Path(path))
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


def object_mesh(obj: ObjectSpec, index: int, label: str) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, triangles) of scene object ``index`` in its own frame; a missing or unusable
    mesh file is a SceneError of file ``label``."""
    if obj.primitive is not None:
        return _primitive_mesh(obj.primitive)
    if obj.mesh is None:  # the scene reader requires one of the two
        raise SceneError(label, f"objects[{index}]", "object has neither a mesh nor a primitive", ["mesh", "primitive"])
    path = resolve_path(obj.mesh)
    if not Path(path).is_file():
        raise SceneError(
            label,
            f"objects[{index}].mesh",
            f"mesh file {obj.mesh!r} not found",
            "a mesh path relative to the repository, e.g. assets/ycb/MustardBottle.obj",
        )
    verts, tris, problem = _load_mesh_file(str(path))
    if problem:
        raise SceneError(
            label,
            f"objects[{index}].mesh",
            f"{obj.mesh}: {problem}",
            "a non-empty, edge- and vertex-manifold triangle mesh (OBJ/PLY/STL, metres)",
        )
    return verts, tris


def table_mesh(table: TableSpec) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, triangles) of the table in ``world``: a box whose top is at z = 0."""
    sx, sy = table.size_m
    box = o3d.geometry.TriangleMesh.create_box(sx, sy, table.thickness_m)
    box.translate((table.center_m[0] - sx / 2, table.center_m[1] - sy / 2, -table.thickness_m))
    return np.asarray(box.vertices), np.asarray(box.triangles, dtype=np.int32)


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
# The placed objects
# --------------------------------------------------------------------------------------


class SceneObjects:
    """The objects of a scene (effects resolved, ``sim.effects``) placed in ``world``: per
    object, in scene order, its object-to-world transform, its world-frame mesh (vertices,
    triangles) and bounds. With ``check``, an object reaching outside the workspace is a
    SceneError of file ``label``; a bad mesh always is."""

    def __init__(self, scene: Scene, label: str, check: bool = False):
        self.specs = scene.objects
        relief_effect = scene.effect("micro_relief")
        self.relief_scale = float(relief_effect.params["scale"]) if relief_effect else 0.0
        self.object_to_world: list[np.ndarray] = []
        self.meshes: list[tuple[np.ndarray, np.ndarray]] = []  # world-frame vertices, triangles
        self.aabbs: list[tuple[np.ndarray, np.ndarray]] = []  # world-frame bounds
        for i, obj in enumerate(scene.objects):
            verts, tris = object_mesh(obj, i, label)
            R = _rot_z(obj.yaw_rad)
            z = obj.z_m if obj.z_m is not None else -float(verts[:, 2].min())
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = (obj.x_m, obj.y_m, z)
            world_verts = verts @ R.T + T[:3, 3]
            lo, hi = world_verts.min(0), world_verts.max(0)
            if check:
                _check_inside_workspace(scene, i, lo, hi, label)
            self.object_to_world.append(T)
            self.meshes.append((world_verts, tris))
            self.aabbs.append((lo, hi))
        self.relief_objects = [i for i, o in enumerate(scene.objects) if o.relief and self.relief_scale > 0]
        # Sphere primitives are ray-cast on their tessellation, then the hit is moved onto the
        # analytic sphere (float precision instead of the tessellation's chord error).
        self.spheres = {
            i: (self.object_to_world[i][:3, 3].copy(), float(o.primitive["sphere"]))
            for i, o in enumerate(scene.objects)
            if o.primitive and "sphere" in o.primitive
        }

    def refine_spheres(
        self,
        rays: np.ndarray,
        t: np.ndarray,
        gids: np.ndarray,
        normals: np.ndarray | None,
        geom_to_object: dict[int, int],
    ) -> None:
        """In place: hits on sphere primitives moved onto the analytic sphere (t, normals)."""
        for gid, oi in geom_to_object.items():
            if oi not in self.spheres:
                continue
            idx = np.flatnonzero(gids == gid)
            if idx.size == 0:
                continue
            centre, radius = self.spheres[oi]
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

    def relief_dt(self, oi: int, p_world: np.ndarray, ndotd: np.ndarray, dnorm: np.ndarray) -> np.ndarray:
        """Change of the ray parameter when the surface is pushed out by the relief: the
        displaced tangent plane n.x = n.p + h is met at t + h / (n.d) (n.d < 0 when facing)."""
        T = self.object_to_world[oi]
        p_obj = (p_world - T[:3, 3]) @ T[:3, :3]
        h_m = relief_height_mm(self.specs[oi].relief, p_obj, self.relief_scale) * 1e-3
        denom = np.minimum(ndotd, -0.1 * dnorm)  # facing side; grazing clamped
        return (h_m / denom).astype(np.float32)


def _check_inside_workspace(scene: Scene, index: int, lo: np.ndarray, hi: np.ndarray, label: str) -> None:
    if np.any(lo < scene.workspace_min_m - 1e-6) or np.any(hi > scene.workspace_max_m + 1e-6):
        raise SceneError(
            label,
            f"objects[{index}].pose",
            f"object {scene.objects[index].name!r} spans {lo.round(3).tolist()}..{hi.round(3).tolist()} m, "
            "outside the workspace",
            f"workspace min_m {scene.workspace_min_m.tolist()} .. max_m {scene.workspace_max_m.tolist()}",
        )
