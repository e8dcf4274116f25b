"""The simulated world: scenes that simulate only the effects they call for.

- ``sim.scene``: scene files (YAML), their validation (:class:`SceneError`) and the effect
  registry (:data:`EFFECTS`).
- ``sim.world``: :class:`SimWorld` (Open3D ray casting: depth frames, grasp contact).
- ``sim.depth_effects``: Kinect v2 depth effects; ``sim.arm``: arm motion model.
- ``sim.gelsight``: the GelSight renderer (its own part).

Names are imported lazily so ``import sim.gelsight`` does not load Open3D.
"""
from __future__ import annotations

__all__ = ["EFFECTS", "Scene", "SceneError", "load_scene", "SimWorld", "GraspContact", "FingerContact"]


def __getattr__(name: str):
    if name in ("EFFECTS", "Scene", "SceneError", "load_scene"):
        from sim import scene

        return getattr(scene, name)
    if name in ("SimWorld", "GraspContact", "FingerContact"):
        from sim import world

        return getattr(world, name)
    raise AttributeError(f"module 'sim' has no attribute {name!r}")
