"""Depth cameras of the simulated world: z-depth images ray-cast from a scene's cameras.

:class:`DepthRenderer` casts each camera's pixel rays against the table and the placed objects
(``sim.meshes``) and gives the z-depth image (float32 metres, NaN = no return): exact geometry
when the scene calls for no effect, else with the scene's depth effects
(``sim/depth_effects.py``) and object micro-relief.

Depth frames: the world is static (objects do not move and the robot is not drawn), so
each camera's exact ray cast is done once and cached; a frame then costs its effects only.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import open3d as o3d
import open3d.core as o3c
from scipy import ndimage

from sim.depth_effects import DepthEffectChain, LateralNoise, gaussian
from sim.effects import DEPTH_EFFECT_ORDER
from sim.meshes import SceneObjects, table_mesh
from sim.seeding import state_rng
from workcell.parts import CameraSpec
from workcell.scene import Scene, SceneError

# Open3D tensors are made on the CPU with the dtype of the array they copy.
_CPU = o3c.Device("CPU:0")


@dataclasses.dataclass
class LateralPixels:
    """How the lateral-noise effect samples one camera's exact cast: pixels whose jittered ray
    may land on another surface are re-cast each frame; elsewhere the jittered sample follows
    from the local inverse-depth gradient (:meth:`DepthRenderer._split_lateral_pixels`)."""

    noise: LateralNoise
    recast_idx: np.ndarray  # flat indices of the pixels re-cast each frame
    smooth_idx: np.ndarray  # flat indices of the others
    inv_z_smooth: np.ndarray  # float32 1/z of the smooth pixels
    lateral_scale_smooth: np.ndarray  # float32 sigma of their jittered 1/z


@dataclasses.dataclass
class ExactCast:
    """A camera's exact ray cast (true pose, micro-relief included), made once: what each of
    its frames reuses."""

    z: np.ndarray  # H*W float32 z-depth, NaN = no return
    cos_incidence: np.ndarray | None  # H*W float32, where the effects need it
    static: dict  # per-pixel quantities of the exact cast the effects reuse
    lateral: LateralPixels | None  # with the lateral-noise effect only


@dataclasses.dataclass
class SimCamera:
    """One camera of the scene: its pixel rays and what its frames reuse."""

    spec: CameraSpec
    nominal_to_world: np.ndarray
    true_to_world: np.ndarray
    effects: DepthEffectChain
    u: np.ndarray  # H*W float32 pixel columns
    v: np.ndarray
    dirs_cam: np.ndarray  # H*W x 3 float32, z component 1
    rays: o3c.Tensor  # H*W x 6 float32 (true pose)
    dirs_world: np.ndarray
    stream: int  # the camera's noise stream (its index in the scene)
    cache: ExactCast | None = None  # made by the first frame


def _pixel_dirs(cam, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    d = np.empty((u.size, 3), dtype=np.float32)
    d[:, 0] = (u - np.float32(cam.cx)) / np.float32(cam.fx)
    d[:, 1] = (v - np.float32(cam.cy)) / np.float32(cam.fy)
    d[:, 2] = 1.0
    return d


def _rays(camera_to_world: np.ndarray, dirs_cam: np.ndarray) -> tuple[np.ndarray, o3c.Tensor]:
    R = camera_to_world[:3, :3].astype(np.float32)
    dirs_world = np.einsum("ij,kj->ik", dirs_cam, R)
    rays = np.empty((dirs_cam.shape[0], 6), dtype=np.float32)
    rays[:, :3] = camera_to_world[:3, 3].astype(np.float32)
    rays[:, 3:] = dirs_world
    return dirs_world, o3c.Tensor(rays, o3c.float32, _CPU)


def _depth_discontinuities(z: np.ndarray, gids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(valid, disc): pixels with a return, and pixels next to a depth jump, another geometry or
    no return (H x W bool each)."""
    valid = np.isfinite(z)
    disc = np.zeros(z.shape, dtype=bool)
    for axis in (0, 1):
        a = [slice(None)] * 2
        b = [slice(None)] * 2
        a[axis], b[axis] = slice(1, None), slice(None, -1)
        za, zb = z[tuple(a)], z[tuple(b)]
        with np.errstate(invalid="ignore"):
            jump = (valid[tuple(a)] != valid[tuple(b)]) | (gids[tuple(a)] != gids[tuple(b)])
            jump |= np.abs(za - zb) > 0.01 * np.fmin(za, zb)
        jump &= valid[tuple(a)] | valid[tuple(b)]
        disc[tuple(a)] |= jump
        disc[tuple(b)] |= jump
    return valid, disc


class DepthRenderer:
    """The scene's depth cameras looking at the table (geometry id 0) and the ``objects``
    (ids 1..n). ``seed`` keys each camera's default noise stream (``sim.seeding``)."""

    def __init__(self, scene: Scene, objects: SceneObjects, seed: int):
        self.scene = scene
        self.objects = objects
        self.seed = seed
        self.raycast_scene = o3d.t.geometry.RaycastingScene()
        tv, tt = table_mesh(scene.table)
        self.raycast_scene.add_triangles(
            o3c.Tensor(tv.astype(np.float32), o3c.float32, _CPU), o3c.Tensor(tt.astype(np.uint32), o3c.uint32, _CPU)
        )
        self.geom_to_object: dict[int, int] = {}
        for i, (v, t) in enumerate(objects.meshes):
            gid = self.raycast_scene.add_triangles(
                o3c.Tensor(v.astype(np.float32), o3c.float32, _CPU), o3c.Tensor(t.astype(np.uint32), o3c.uint32, _CPU)
            )
            self.geom_to_object[gid] = i
        self.cameras: dict[str, SimCamera] = {}
        for ci, cam in enumerate(scene.cameras):
            self.cameras[cam.name] = self._make_camera(cam, ci)

    def _make_camera(self, cam, index: int) -> SimCamera:
        specs = [self.scene.effect(name, cam.name) for name in DEPTH_EFFECT_ORDER]
        chain = DepthEffectChain([s for s in specs if s is not None])
        nominal = cam.camera_to_world.copy()
        true = nominal @ chain.extrinsic.offset_matrix() if chain.extrinsic else nominal
        vv, uu = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float32)
        u, v = uu.reshape(-1), vv.reshape(-1)
        dirs_cam = _pixel_dirs(cam, u, v)
        dirs_world, rays = _rays(true, dirs_cam)
        return SimCamera(cam, nominal, true, chain, u, v, dirs_cam, rays, dirs_world, index)

    def check_cameras_see_workspace(self, label: str) -> None:
        """Each camera sees part of the workspace, else a SceneError of file ``label``."""
        for ci, cam in enumerate(self.scene.cameras):
            self._check_camera_sees_workspace(cam, ci, label)

    def _check_camera_sees_workspace(self, cam, index: int, label: str) -> None:
        c = self.cameras[cam.name]
        step = 8
        sel = (c.u.astype(int) % step == 0) & (c.v.astype(int) % step == 0)
        rays = c.rays.numpy()[sel]
        ans = self.raycast_scene.cast_rays(o3c.Tensor(np.ascontiguousarray(rays), o3c.float32, _CPU))
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
        cast = self._exact_cast(c) if c.cache is None else c.cache
        z, cos_inc = cast.z, cast.cos_incidence
        if cast.lateral is not None:
            z, cos_inc = self._lateral(c, cast, cast.lateral, rng)
        else:
            z = z.copy()
        z = z.reshape(cam.height, cam.width)
        if cos_inc is not None:
            cos_inc = cos_inc.reshape(cam.height, cam.width)
        return chain.measure(z, cos_inc, rng, cast.static, None if cast.lateral is None else cast.lateral.recast_idx)

    def _cast_camera(
        self, c: SimCamera, rays: o3c.Tensor, dirs_world: np.ndarray, nthreads: int = 0
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Exact cast: (z-depth float32 with NaN, cos incidence float32 or None, geometry ids)."""
        ans = self.raycast_scene.cast_rays(rays, nthreads=nthreads)
        # Ray directions have a camera-frame z component of exactly 1, so the hit parameter
        # is the z-depth itself (not the ray length).
        z = ans["t_hit"].numpy()
        gids = ans["geometry_ids"].numpy()
        cos_inc = None
        need_normals = c.effects.needs_incidence or bool(self.objects.relief_objects)
        n = ans["primitive_normals"].numpy() if need_normals else None
        if self.objects.spheres:
            z = z.copy()
            n = None if n is None else n.copy()
            self.objects.refine_spheres(rays.numpy(), z, gids, n, self.geom_to_object)
        if n is not None:  # need_normals
            ndotd = np.einsum("ij,ij->i", n, dirs_world)
            dnorm = np.sqrt(np.einsum("ij,ij->i", dirs_world, dirs_world))
            if self.objects.relief_objects:
                z = self._apply_relief_depth(z, gids, rays, ndotd, dnorm)
            if c.effects.needs_incidence:
                cos_inc = (np.abs(ndotd) / dnorm).astype(np.float32)
        z = np.where(np.isfinite(z), z, np.float32(np.nan)).astype(np.float32, copy=False)
        return z, cos_inc, gids

    def _exact_cast(self, c: SimCamera) -> ExactCast:
        """Cast ``c``'s rays exactly and keep the cast (``c.cache``)."""
        z, cos_inc, gids = self._cast_camera(c, c.rays, c.dirs_world)
        static = c.effects.prepare(
            z.reshape(c.spec.height, c.spec.width),
            None if cos_inc is None else cos_inc.reshape(c.spec.height, c.spec.width),
        )
        lateral = None if c.effects.lateral is None else self._split_lateral_pixels(c, c.effects.lateral, z, gids)
        c.cache = ExactCast(z, cos_inc, static, lateral)
        return c.cache

    def _split_lateral_pixels(
        self, c: SimCamera, noise: LateralNoise, z: np.ndarray, gids: np.ndarray
    ) -> LateralPixels:
        # Pixels whose jittered ray may land on another surface (depth jump, another
        # geometry, no return) within the jitter radius are re-cast each frame; elsewhere the
        # jittered sample follows from the local inverse-depth gradient (exact on planes).
        h, w = c.spec.height, c.spec.width
        zi = z.reshape(h, w)
        valid, disc = _depth_discontinuities(zi, gids.reshape(h, w).astype(np.int64))
        # A jump lies half a pixel beyond a flagged pixel, so a pixel ``radius`` away from
        # every flagged one keeps its jittered sample (|jitter| <= 3 sigma) on its own surface.
        radius = max(1, int(math.ceil(3.0 * noise.sigma_px - 0.5)))
        near = ndimage.binary_dilation(disc, structure=np.ones((3, 3), bool), iterations=radius)
        near &= ndimage.binary_dilation(valid, structure=np.ones((3, 3), bool), iterations=radius)
        smooth_idx = np.flatnonzero(valid & ~near)
        inv_z = np.where(valid, 1.0 / np.where(valid, zi, 1.0), 0.0)
        gv, gu = np.gradient(inv_z)  # central differences: exact for 1/z affine (planes)
        # gu du + gv dv with du, dv ~ N(0, s^2) is N(0, s^2 (gu^2 + gv^2)): one draw per pixel
        grad = np.hypot(gu, gv).reshape(-1)[smooth_idx]
        return LateralPixels(
            noise,
            recast_idx=np.flatnonzero(near),
            smooth_idx=smooth_idx,
            inv_z_smooth=inv_z.reshape(-1)[smooth_idx].astype(np.float32),
            lateral_scale_smooth=(grad * noise.sigma_px).astype(np.float32),
        )

    def _lateral(
        self, c: SimCamera, cast: ExactCast, lat: LateralPixels, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray | None]:
        cam = c.spec
        sigma = np.float32(lat.noise.sigma_px)
        limit = np.float32(3.0 * lat.noise.sigma_px)  # jitter truncated at 3 sigma
        z = np.full(cast.z.shape, np.nan, dtype=np.float32)
        cos_inc = None if cast.cos_incidence is None else cast.cos_incidence.copy()
        # smooth pixels: 1/z is affine in (u, v) on a plane, so the jittered sample is
        # 1 / (1/z + d(1/z)/du du + d(1/z)/dv dv) (exact on planes, first order elsewhere)
        idx = lat.smooth_idx
        n = np.clip(gaussian(rng, idx.size), -3.0, 3.0)
        z[idx] = 1.0 / (lat.inv_z_smooth + lat.lateral_scale_smooth * n)
        # pixels near discontinuities: cast the jittered rays exactly
        idx = lat.recast_idx
        if idx.size:
            jit = np.clip(gaussian(rng, 2 * idx.size).reshape(2, idx.size) * sigma, -limit, limit)
            dirs_cam = _pixel_dirs(cam, c.u[idx] + jit[0], c.v[idx] + jit[1])
            dirs_world, rays = _rays(c.true_to_world, dirs_cam)
            # a few thousand rays: one thread avoids waiting on a busy machine's other cores
            zr, cr, _ = self._cast_camera(c, rays, dirs_world, nthreads=1)
            z[idx] = zr
            if cos_inc is not None:
                cos_inc[idx] = cr
        return z, cos_inc

    def _apply_relief_depth(self, t, geom_ids, rays, ndotd, dnorm):
        rays_np = rays.numpy() if isinstance(rays, o3c.Tensor) else rays
        t = t.copy()
        for gid, oi in self.geom_to_object.items():
            if oi not in self.objects.relief_objects:
                continue
            idx = np.flatnonzero(geom_ids == gid)
            if idx.size == 0:
                continue
            r = rays_np[idx]
            p = r[:, :3] + t[idx, None] * r[:, 3:]
            t[idx] = t[idx] + self.objects.relief_dt(oi, p, ndotd[idx], dnorm[idx])
        return t

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
