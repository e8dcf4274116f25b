"""Grasp contact in the simulated world: where the two gels of a top-down grasp touch the
objects, how deep they press at a given force, and the per-pixel gel gap maps (mm in the gel
frame) the GelSight renderer turns into images.

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
"""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
import open3d.core as o3c

from sim.meshes import SceneObjects
from workcell.compliance import contact_grid_shape, indentation_for_force_mm
from workcell.kinematics import gel_poses_world
from workcell.scene import Scene

# How far behind the gel plane gap-map rays start (mm): surfaces up to this deep in the gel
# are still measured.
_BACK_OFF_MM = 5.0
# Open3D tensors are made on the CPU with the dtype of the array they copy.
_CPU = o3c.Device("CPU:0")


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
    # The world's gels that computed this contact: they cast the gap maps of other sizes.
    world: GelContact = dataclasses.field(repr=False)
    # Each finger closes to its own contact, as if the object slid to sit between the fingers;
    # the midpoint of the two gels ends this far from the TCP along tool +y (0 when centred).
    centre_shift_m: float = 0.0

    def gap_map(self, finger: str, size: tuple[int, int], extent_mm: tuple[float, float] | None = None) -> np.ndarray:
        """The gap map of ``finger`` at another size (same contact)."""
        fc = self.fingers[finger]
        return self.world.gap_map(fc.gel_to_world, size, extent_mm)


def gel_grid(size: tuple[int, int], extent_mm: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Gel-frame (x, z) in metres of the pixel centres of an H x W map covering
    ``extent_mm = (along rows = gel z, along columns = gel x)``; both arrays H x W.
    Rows run along gel z and columns along gel x, as in ``perception.depthmap``."""
    h, w = int(size[0]), int(size[1])
    ez, ex = float(extent_mm[0]) * 1e-3, float(extent_mm[1]) * 1e-3
    z = (np.arange(h) - (h - 1) / 2.0) * (ez / h)
    x = (np.arange(w) - (w - 1) / 2.0) * (ex / w)
    zz, xx = np.meshgrid(z, x, indexing="ij")
    return xx, zz


class GelContact:
    """The gripper's gels against the scene's placed ``objects`` (ray cast on the objects
    alone: the table is not in the way of a gel)."""

    def __init__(self, scene: Scene, objects: SceneObjects):
        self.scene = scene
        self.objects = objects
        self.raycast_scene = o3d.t.geometry.RaycastingScene()
        self.geom_to_object: dict[int, int] = {}
        for i, (v, t) in enumerate(objects.meshes):
            gid = self.raycast_scene.add_triangles(
                o3c.Tensor(v.astype(np.float32), o3c.float32, _CPU), o3c.Tensor(t.astype(np.uint32), o3c.uint32, _CPU)
            )
            self.geom_to_object[gid] = i

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
        ans = self.raycast_scene.cast_rays(o3c.Tensor(rays, o3c.float32, _CPU))
        t = ans["t_hit"].numpy().astype(np.float64)
        hit = np.isfinite(t)
        if not np.any(hit):
            return t, hit
        n = ans["primitive_normals"].numpy()
        if self.objects.spheres:
            n = n.copy()
            self.objects.refine_spheres(rays, t, ans["geometry_ids"].numpy(), n, self.geom_to_object)
        ndotd = n @ R[:, 1]
        front = hit & (ndotd < 0)
        if self.objects.relief_objects:
            self._apply_relief(rays, t, front, ans["geometry_ids"].numpy(), ndotd)
        return t, front

    def _apply_relief(self, rays: np.ndarray, t: np.ndarray, front: np.ndarray, gids: np.ndarray, ndotd) -> None:
        """In place: front-facing hits on relief objects moved onto the displaced surface."""
        for gid, oi in self.geom_to_object.items():
            if oi not in self.objects.relief_objects:
                continue
            idx = np.flatnonzero(front & (gids == gid))
            if idx.size:
                p = rays[idx, :3] + t[idx, None] * rays[idx, 3:]
                t[idx] += self.objects.relief_dt(oi, p, ndotd[idx], np.ones(idx.size))

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
        return any(np.all(hi >= olo) and np.all(lo <= ohi) for olo, ohi in self.objects.aabbs)

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
        x, z = gel_grid(size, extent_mm)
        t, front = self._cast_from_gel(gel_to_world, x, z, _BACK_OFF_MM * 1e-3)
        gap = np.full(t.shape, np.inf)
        gap[front] = t[front] * 1e3 - _BACK_OFF_MM - indentation_mm
        inside = np.isfinite(t) & ~front  # ray started inside an object: deeply pressed
        gap[inside] = -_BACK_OFF_MM - indentation_mm
        return gap.reshape(int(size[0]), int(size[1])).astype(np.float32)

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
        open_poses = gel_poses_world(tcp_pose_world, gr.max_width_m, self.scene.gripper_geometry())
        fingers: dict[str, FingerContact] = {}
        gaps: dict[str, np.ndarray] = {}
        grid = self._contact_grid()
        size = (self.scene.gelsight.image_height, self.scene.gelsight.image_width) if size is None else size
        for finger, pose in open_poses.items():
            fingers[finger] = self._close_finger(finger, pose, force_n, grid)
            if finger in gap_fingers:
                gaps[finger] = self.gap_map(fingers[finger].gel_to_world, size, extent_mm)
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

    def _contact_grid(self) -> tuple[np.ndarray, np.ndarray, float]:
        """(x, z, cell area mm^2): the grid over the whole gel that finds the first touch and
        balances the force."""
        gel_size_m = self.scene.gripper.gel_size_m
        shape, cell_area_mm2 = contact_grid_shape(gel_size_m)
        x, z = gel_grid(shape, (gel_size_m[1] * 1e3, gel_size_m[0] * 1e3))
        return x, z, cell_area_mm2

    def _close_finger(
        self, finger: str, open_pose: np.ndarray, force_n: float, grid: tuple[np.ndarray, np.ndarray, float]
    ) -> FingerContact:
        """One finger closed from ``open_pose`` (its gel at the open gripper) until it meets the
        object on the contact ``grid``, then pressed with ``force_n``."""
        x, z, cell_area = grid
        max_travel = self.scene.gripper.max_width_m / 2.0
        t, front = self._cast_from_gel(open_pose, x, z, 0.0)
        collision = bool(np.any(np.isfinite(t) & ~front))
        reach = front & (t <= max_travel)
        if collision or not np.any(reach):
            travel = max_travel if not collision else 0.0
            in_contact, d, area, sat = False, 0.0, 0.0, False
        else:
            travel = float(t[reach].min())
            gap_local = np.where(front, (t - travel) * 1e3, np.inf)
            gripper = self.scene.gripper
            d, area, sat = indentation_for_force_mm(
                gap_local,
                cell_area,
                force_n,
                gripper.foundation_stiffness_n_per_mm3,
                gripper.elastomer_thickness_m * 1e3,
            )
            in_contact = True
        # after the first touch the finger keeps closing by d while the gel compresses
        travel = min(travel + d * 1e-3, max_travel) if in_contact else travel
        gel = open_pose.copy()
        gel[:3, 3] += travel * open_pose[:3, 1]
        return FingerContact(finger, gel, in_contact, travel, d, area, sat, collision)

    def contact_width_m(self, tcp_pose_world: np.ndarray, force_n: float = 0.0) -> float | None:
        """Gripper width (m) at which closing at ``tcp_pose_world`` holds the object with
        ``force_n`` (the gels compressed by it), or None when neither finger meets anything:
        what the simulated gripper's ``contact_width_m()`` callback needs."""
        contact = self.grasp_contact(tcp_pose_world, force_n, gap_fingers=())
        if not any(f.in_contact for f in contact.fingers.values()):
            return None
        return contact.width_m
