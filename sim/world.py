"""The simulated world: objects on a table, seen by depth cameras and touched by the gels.

:class:`SimWorld` builds, from a validated :class:`workcell.scene.Scene`, an Open3D
``RaycastingScene`` of the table and the objects (meshes in metres, placed in ``world``:
``sim.meshes``), and answers two questions:

- :meth:`SimWorld.render_depth` — the z-depth image (float32 metres, NaN = no return) a
  camera sees, exact geometry when the scene calls for no effect, else with the scene's
  depth effects (``sim/depth_effects.py``) and object micro-relief (``sim.depth_render``).
- :meth:`SimWorld.grasp_contact` — where the two gels of a top-down grasp touch the object,
  how deep they press at a given force, and the per-pixel gel gap maps (mm in the gel frame)
  the GelSight renderer turns into images (``sim.grasp_contact``: the gap-map layout and the
  gel's compliance model).
"""

from __future__ import annotations

import os

import numpy as np

from sim.depth_render import DepthRenderer
from sim.effects import resolve_effects
from sim.grasp_contact import GelContact, GraspContact
from sim.meshes import SceneObjects
from workcell.scene import Scene, load_scene, resolve_path


class SimWorld:
    """Ray-cast world of one scene. ``seed`` (default: the scene's) seeds every effect's
    draws (``sim.seeding``); two worlds with the same scene and seed produce identical frames.

    It owns the placed objects (``objects``, :class:`sim.meshes.SceneObjects`), the depth
    cameras (``depth``, :class:`sim.depth_render.DepthRenderer`) and the gels (``gels``,
    :class:`sim.grasp_contact.GelContact`), and hands each question to the part that answers it."""

    def __init__(self, scene: Scene, seed: int | None = None, check: bool = False, file_label: str | None = None):
        scene = resolve_effects(scene)
        self.scene = scene
        self.seed = scene.seed if seed is None else int(seed)
        label = file_label or scene.path
        self.objects = SceneObjects(scene, label, check)
        self.depth = DepthRenderer(scene, self.objects, self.seed)
        self.gels = GelContact(scene, self.objects)
        if check:
            self.depth.check_cameras_see_workspace(label)
        self.relief_scale = self.objects.relief_scale
        self.object_to_world = self.objects.object_to_world
        self.object_meshes = self.objects.meshes  # world-frame vertices, triangles
        self.object_aabbs = self.objects.aabbs  # world-frame bounds
        self.cameras = self.depth.cameras

    @classmethod
    def from_file(cls, path: str | os.PathLike, seed: int | None = None) -> SimWorld:
        """The world of a scene file, checked completely: the workcell (workcell.scene), the
        effects (sim.effects), the meshes (non-empty, manifold), every object inside the
        workspace and every camera seeing part of it. Each problem is a SceneError."""
        return cls(load_scene(path), seed=seed, check=True, file_label=str(path))

    # ---------------------------------------------------------------- depth (sim.depth_render)
    def camera_names(self) -> list[str]:
        return self.depth.camera_names()

    def nominal_camera_to_world(self, camera: str) -> np.ndarray:
        """See :meth:`sim.depth_render.DepthRenderer.nominal_camera_to_world`."""
        return self.depth.nominal_camera_to_world(camera)

    def true_camera_to_world(self, camera: str) -> np.ndarray:
        return self.depth.true_camera_to_world(camera)

    def render_depth(self, camera: str, rng: np.random.Generator | None = None) -> np.ndarray:
        """See :meth:`sim.depth_render.DepthRenderer.render_depth`."""
        return self.depth.render_depth(camera, rng)

    def point_cloud(self, camera: str, depth: np.ndarray | None = None, nominal: bool = True) -> np.ndarray:
        """See :meth:`sim.depth_render.DepthRenderer.point_cloud`."""
        return self.depth.point_cloud(camera, depth, nominal)

    # ---------------------------------------------------------------- contact (sim.grasp_contact)
    def default_extent_mm(self) -> tuple[float, float]:
        return self.gels.default_extent_mm()

    def near_gel(
        self, gel_to_world: np.ndarray, extent_mm: tuple[float, float] | None = None, reach_m: float = 0.01
    ) -> bool:
        """See :meth:`sim.grasp_contact.GelContact.near_gel`."""
        return self.gels.near_gel(gel_to_world, extent_mm, reach_m)

    def gap_map(
        self,
        gel_to_world: np.ndarray,
        size: tuple[int, int],
        extent_mm: tuple[float, float] | None = None,
        indentation_mm: float = 0.0,
    ) -> np.ndarray:
        """See :meth:`sim.grasp_contact.GelContact.gap_map`."""
        return self.gels.gap_map(gel_to_world, size, extent_mm, indentation_mm)

    def grasp_contact(
        self,
        tcp_pose_world: np.ndarray,
        force_n: float,
        size: tuple[int, int] | None = None,
        extent_mm: tuple[float, float] | None = None,
        gap_fingers: tuple[str, ...] = ("left", "right"),
    ) -> GraspContact:
        """See :meth:`sim.grasp_contact.GelContact.grasp_contact`."""
        return self.gels.grasp_contact(tcp_pose_world, force_n, size, extent_mm, gap_fingers)

    def contact_width_m(self, tcp_pose_world: np.ndarray, force_n: float = 0.0) -> float | None:
        """See :meth:`sim.grasp_contact.GelContact.contact_width_m`."""
        return self.gels.contact_width_m(tcp_pose_world, force_n)


# Worlds shared by the simulated backends of one process (same scene file and seed).
_WORLDS: dict[tuple[str, int | None], SimWorld] = {}


def shared_world(scene_path: str, seed: int | None = None) -> SimWorld:
    """The SimWorld of ``scene_path`` (loaded and checked once per process and seed)."""
    key = (str(resolve_path(scene_path)), seed)
    if key not in _WORLDS:
        _WORLDS[key] = SimWorld.from_file(scene_path, seed=seed)
    return _WORLDS[key]
