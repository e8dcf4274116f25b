"""A contact library: many kinds of contact, made cheaply by the simulated world, in exactly the
geometry of a scene's collection sessions (``dtx dataset library OUT --scene SCENE``).

A session holds what three objects feel like under one grasp force. A model trained on it alone
learns those objects' habits, not what a contact looks like: on real presses of a 4 mm ball it
drew the sensor's background (``dtx evaluate --real-presses``). The library shows it contact
itself — spheres and cylinders of 1–15 mm radius, wedges, box corners and faces, textured planes
(ridges, bumps) and random smooth height fields; tilted, placed anywhere on the gel, pressed
0.05–2 mm deep, and a tenth of them held just short of the gel (surface in view, no contact).

Each sample is made as a collected pair is made, with the same code:

* **depth-map**: the surface sampled as a model cloud at ``MODEL_POINT_SPACING_M`` (a jittered
  grid over the crop) and binned by ``perception.depthmap.contact_depth_map`` with the scene's
  gripper geometry, the margin and the depth range of the sessions it joins;
* **tactile image**: the surface as a gel gap map at the scene's GelSight size, rendered by the
  scene's GelSight with the effects the scene calls for (``sim.gelsight.scene_renderer``), then
  brought to the dataset's size by ``dataset.images.resize_rgb``, as the collector does.

The object name of a sample is its family, so leave-one-object-out can hold a family out. The
YCB meshes stay out of the library: the ones the default scene does not use are the unseen
objects a model is judged on (``scenes/ycb_unseen.yaml``). The real GelSight frames are never
used: they are for evaluation only.
"""

from __future__ import annotations

import os

import numpy as np

from dataset.images import resize_rgb, subtract_background
from dataset.records import DatasetError, DatasetInfo, code_version
from dataset.synth import SurfaceMm, gel_gap_from_surface
from dataset.writer import DatasetWriter
from msgs.progress import track
from perception.depthmap import MODEL_POINT_SPACING_M, DepthMapParams, contact_depth_map, crop_bounds
from perception.errors import DepthMapError
from sim.effects import effects_of, resolve_effects
from sim.gelsight import GelSightRenderer, scene_renderer
from workcell.kinematics import GripperGeometry
from workcell.scene import Scene, load_scene

FAMILIES = ("sphere", "cylinder", "wedge", "corner", "textured", "height_field")
# The share of samples whose surface stops short of the gel: in view of the depth camera, not felt.
NO_CONTACT_SHARE = 0.1
DEFAULT_DEPTH_RANGE_M = (-0.005, 0.01)  # what collection sessions use (nodes.collector)


def random_surface_mm(family: str, rng: np.random.Generator) -> SurfaceMm:
    """A surface height y(x, z) in the gel frame, all mm (+inf where the object has no surface
    facing the gel), before it is placed: its contact region is near the origin."""
    angle = rng.uniform(0.0, np.pi)
    cos_a, sin_a = np.cos(angle), np.sin(angle)
    tilt = rng.uniform(-0.15, 0.15, size=2)

    def local(x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return x * cos_a + z * sin_a, -x * sin_a + z * cos_a

    def tilted(y: np.ndarray, x: np.ndarray, z: np.ndarray) -> np.ndarray:
        return y + tilt[0] * x + tilt[1] * z

    if family == "sphere":
        radius = float(np.exp(rng.uniform(np.log(1.0), np.log(12.0))))
        return lambda x, z: _cap(x**2 + z**2, radius)
    if family == "cylinder":
        radius = float(np.exp(rng.uniform(np.log(1.0), np.log(15.0))))
        return lambda x, z: tilted(_cap(local(x, z)[0] ** 2, radius), x, z)
    if family == "wedge":
        slope = rng.uniform(0.2, 2.0)
        return lambda x, z: tilted(slope * np.abs(local(x, z)[0]), x, z)
    if family == "corner":
        quadrant = bool(rng.integers(2))  # a box's corner, or the edge of its face

        def corner(x: np.ndarray, z: np.ndarray) -> np.ndarray:
            u, v = local(x, z)
            on_face = (u > 0) & ((v > 0) | (not quadrant))
            return np.where(on_face, tilted(np.zeros_like(u), x, z), np.inf)

        return corner
    if family == "textured":
        amplitude, period = rng.uniform(0.05, 0.4), rng.uniform(0.8, 4.0)
        bumps = bool(rng.integers(2))

        def textured(x: np.ndarray, z: np.ndarray) -> np.ndarray:
            u, v = local(x, z)
            wave = 0.5 * (1.0 - np.cos(2 * np.pi * u / period))
            if bumps:
                wave = wave * 0.5 * (1.0 - np.cos(2 * np.pi * v / period))
            return tilted(amplitude * wave, x, z)

        return textured
    if family == "height_field":
        count = int(rng.integers(3, 9))
        centres = rng.uniform(-6.0, 6.0, size=(count, 2))
        sigmas = rng.uniform(1.0, 5.0, size=count)
        heights = rng.uniform(0.2, 2.0, size=count)

        def field(x: np.ndarray, z: np.ndarray) -> np.ndarray:
            y = np.zeros(np.broadcast(x, z).shape)
            for (cx, cz), sigma, height in zip(centres, sigmas, heights):
                y -= height * np.exp(-((x - cx) ** 2 + (z - cz) ** 2) / (2 * sigma**2))
            return tilted(y, x, z)

        return field
    raise DatasetError(f"unknown contact family {family!r} (known: {FAMILIES})")


def _cap(r2_mm2: np.ndarray, radius_mm: float) -> np.ndarray:
    """Lower surface of a sphere (or cylinder) of ``radius_mm`` whose lowest point is at y = 0."""
    inside = r2_mm2 < radius_mm**2
    return np.where(inside, radius_mm - np.sqrt(np.where(inside, radius_mm**2 - r2_mm2, 0.0)), np.inf)


def placed(surface: SurfaceMm, offset_mm: tuple[float, float], lift_mm: float) -> SurfaceMm:
    """``surface`` moved by ``offset_mm`` (x, z) along the gel and ``lift_mm`` away from it."""
    return lambda x, z: surface(x - offset_mm[0], z - offset_mm[1]) + lift_mm


def surface_cloud_m(
    surface: SurfaceMm,
    half_x_m: float,
    half_z_m: float,
    rng: np.random.Generator,
    spacing_m: float = MODEL_POINT_SPACING_M,
) -> np.ndarray:
    """The surface sampled as a model cloud (N x 3, gel frame, m): one point per ``spacing_m``²
    of the crop's x-z area, jittered within its cell; where the surface has no height, none."""
    nx, nz = int(np.ceil(2 * half_x_m / spacing_m)), int(np.ceil(2 * half_z_m / spacing_m))
    x = -half_x_m + (np.arange(nx)[None, :] + rng.uniform(size=(nz, nx))) * (2 * half_x_m / nx)
    z = -half_z_m + (np.arange(nz)[:, None] + rng.uniform(size=(nz, nx))) * (2 * half_z_m / nz)
    y = surface(x * 1e3, z * 1e3) * 1e-3
    keep = np.isfinite(y)
    return np.stack([x[keep], y[keep], z[keep]], axis=1)


def library_sample(
    family: str,
    rng: np.random.Generator,
    geometry: GripperGeometry,
    params: DepthMapParams,
    renderer: GelSightRenderer,
    size: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """One (depth-map m, tactile image uint8 at ``size``, model_to_gel) sample of ``family``, or
    None when the drawn surface leaves nothing in the crop (drawn again by the caller).
    ``model_to_gel`` (4 x 4, m) places the drawn shape's own origin in the gel frame: where the
    gel was on that "object", which tells two libraries' contacts apart (dataset.splits'
    twins). Its in-plane angle is not in it, so the rule may join two contacts that differ only
    by their angle: more grasps kept to one split than need be, never fewer."""
    half_x, half_z, _, _ = crop_bounds(geometry, params)
    sensed_x_mm, sensed_z_mm = (0.5e3 * e for e in geometry.sensed_extent_m)
    offset = (rng.uniform(-0.8, 0.8) * sensed_x_mm, rng.uniform(-0.8, 0.8) * sensed_z_mm)
    shape = placed(random_surface_mm(family, rng), offset, 0.0)
    # The press is set by the surface's lowest point over the sensed area, where the gel is.
    probe_x, probe_z = np.meshgrid(
        np.linspace(-sensed_x_mm, sensed_x_mm, 81), np.linspace(-sensed_z_mm, sensed_z_mm, 61)
    )
    lowest = float(np.min(shape(probe_x, probe_z)))
    if not np.isfinite(lowest):
        return None
    press_mm = rng.uniform(-3.0, -0.1) if rng.uniform() < NO_CONTACT_SHARE else rng.uniform(0.05, 2.0)
    lift_mm = -lowest - press_mm
    surface = placed(shape, (0.0, 0.0), lift_mm)
    cloud = surface_cloud_m(surface, half_x, half_z, rng)
    try:
        depth_map = contact_depth_map(cloud, np.eye(4), np.eye(4), geometry, params).depth_map_m
    except DepthMapError:  # the crop was checked by the caller: only "no point in the crop" is left
        return None
    gap_mm = gel_gap_from_surface(surface, *renderer.config.shape, renderer.pixel_pitch_mm)
    model_to_gel = np.eye(4)
    model_to_gel[:3, 3] = 1e-3 * np.array([offset[0], lift_mm, offset[1]])
    return depth_map, resize_rgb(renderer.render(gap_mm), *size), model_to_gel


def _drawn(
    family: str,
    rng: np.random.Generator,
    geometry: GripperGeometry,
    params: DepthMapParams,
    renderer: GelSightRenderer,
    size: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`library_sample` of ``family``, drawn again until its surface leaves something in the crop."""
    while (sample := library_sample(family, rng, geometry, params, renderer, (size, size))) is None:
        pass
    return sample


def write_contact_library(
    out: str | os.PathLike[str],
    samples: int,
    seed: int,
    scene: Scene | str,
    depth_range_m: tuple[float, float] = DEFAULT_DEPTH_RANGE_M,
    margin_m: float = 0.002,
    size: int = 100,
    progress: bool = False,
    method: str = "surface",
) -> DatasetWriter:
    """Write ``samples`` library pairs to ``out`` (two per "grasp", as a session's fingers), the
    families in turn, bins by ``method`` (perception.surface); resumed, drawing the same again."""
    if samples <= 0:
        raise DatasetError(f"--samples must be positive, got {samples}")
    # The scene as named (a repository path travels with a checkpoint that records it).
    scene_name = str(scene) if isinstance(scene, (str, os.PathLike)) else scene.path
    scene = resolve_effects(load_scene(scene) if isinstance(scene, (str, os.PathLike)) else scene)
    geometry = scene.gripper_geometry()
    params = DepthMapParams(shape=(size, size), margin_m=margin_m, y_range_m=depth_range_m, method=method)
    half_x, half_z, y_near, y_far = crop_bounds(geometry, params)
    renderer = scene_renderer(scene, effects=True, rng=np.random.default_rng([seed, 1]))
    background = resize_rgb(renderer.background(), size, size)
    info = DatasetInfo(
        image_height=size,
        image_width=size,
        depth_range_m=depth_range_m,
        scene=scene_name,
        effects=tuple(e.name for e in effects_of(scene, "gelsight")),
        code_version=code_version(),
        split_seed=seed,
        depth_crop_m=(2 * half_x, y_far - y_near, 2 * half_z),
        depth_map_method=method,
    )
    writer = DatasetWriter(out, info)
    for index in track(range(samples), "contact library", "pairs", enabled=progress):
        family = FAMILIES[index % len(FAMILIES)]
        grasp_id, finger = index // 2, ("left", "right")[index % 2]
        sample_id = f"{family}-g{grasp_id:05d}-{finger}"
        if sample_id in writer:
            continue
        # One generator per sample: a resumed run draws exactly the same pairs.
        rng = np.random.default_rng([seed, index])
        renderer.rng = rng  # the sensor noise too: a resumed run renders the same image
        depth_map, tactile, model_to_gel = _drawn(family, rng, geometry, params, renderer, size)
        writer.write(
            sample_id=sample_id,
            object_name=family,
            grasp_id=grasp_id,
            finger=finger,
            grasp_pose=(0.0, 0.0, 0.0, 0.0),
            tactile_rgb=tactile,
            tactile_diff_rgb=subtract_background(tactile, background),
            depth_map_m=depth_map,
            registration_fitness=1.0,
            model_to_gel=model_to_gel,
        )
    return writer
