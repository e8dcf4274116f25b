"""A synthetic tactile dataset, written through the real format, until collection exists.

Each sample is an analytic object surface (sphere, cylinder, box edge, box face, ridges;
random size, position and in-plane angle) pressed a random depth into the gel:

* the depth-map is the min y per bin of that surface over a square crop ``crop_scale``
  times the tactile image's width (the paper's crop is larger than the sensor), sampled
  ``oversample`` x ``oversample`` times per bin; as in perception.depthmap, rows run along
  gel z, columns along gel x, and bins with no surface within reach hold y_far;
* the tactile image is ``sim.gelsight.GelSightRenderer`` rendering the same surface as a
  gel gap (mm per pixel, +inf where there is no surface), at 100 x 100 pixels showing the
  whole 4:3 camera field (19.9 x 14.9 mm), as the paper resized its GelSight frames.

The object name is the shape family, so a leave-one-object-out split holds out a family.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Protocol

import numpy as np

from dataset.images import subtract_background
from dataset.records import DatasetError, DatasetInfo, code_version
from dataset.writer import DatasetWriter
from msgs.progress import track

SHAPES = ("sphere", "cylinder", "edge", "box", "ridges")
SurfaceMm = Callable[[np.ndarray, np.ndarray], np.ndarray]


class TactileRenderer(Protocol):
    def render(self, gel_gap_mm: np.ndarray) -> np.ndarray:
        """H x W gel gap (mm, +inf = nothing) -> H x W x 3 uint8 RGB tactile image."""


def random_surface(shape: str, rng: np.random.Generator) -> SurfaceMm:
    """A surface y(x, z) in the gel frame (all mm; +inf where the object has no surface
    within reach), pressed so that its lowest point is 0.2-1.0 mm into the gel."""
    press_mm = rng.uniform(0.2, 1.0)
    cx, cz = rng.uniform(-3.0, 3.0, size=2)
    angle = rng.uniform(0.0, np.pi)
    cos_a, sin_a = np.cos(angle), np.sin(angle)

    def local(x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (x - cx) * cos_a + (z - cz) * sin_a, -(x - cx) * sin_a + (z - cz) * cos_a

    def cap(r2: np.ndarray, radius: float) -> np.ndarray:
        inside = r2 < radius**2
        return np.where(inside, radius - np.sqrt(np.where(inside, radius**2 - r2, 0.0)) - press_mm, np.inf)

    if shape == "sphere":
        radius = rng.uniform(2.0, 8.0)

        def sphere(x: np.ndarray, z: np.ndarray) -> np.ndarray:
            u, v = local(x, z)
            return cap(u**2 + v**2, radius)

        return sphere
    if shape == "cylinder":
        radius = rng.uniform(2.0, 10.0)
        return lambda x, z: cap(local(x, z)[0] ** 2, radius)
    if shape == "edge":
        slope = rng.uniform(0.3, 1.5)
        return lambda x, z: slope * np.abs(local(x, z)[0]) - press_mm
    if shape == "box":
        half_u, half_v = rng.uniform(2.0, 8.0, size=2)

        def face(x: np.ndarray, z: np.ndarray) -> np.ndarray:
            u, v = local(x, z)
            return np.where((np.abs(u) < half_u) & (np.abs(v) < half_v), -press_mm, np.inf)

        return face
    if shape == "ridges":
        amplitude, period = rng.uniform(0.2, 0.8), rng.uniform(1.0, 4.0)
        return lambda x, z: amplitude * 0.5 * (1.0 - np.cos(2 * np.pi * local(x, z)[0] / period)) - press_mm
    raise DatasetError(f"unknown synthetic shape {shape!r} (known: {SHAPES})")


def depth_map_from_surface(
    surface: SurfaceMm, size: int, crop_mm: float, y_far_m: float, oversample: int = 3
) -> np.ndarray:
    """size x size depth-map (float32 m) of a crop_mm-wide square centred on the gel: the min
    y over ``oversample`` ** 2 samples per bin, y_far_m where nothing is nearer. Settings as
    :func:`analytic_contact_maps` takes them, ``oversample`` an integer in [1, MAX_OVERSAMPLE];
    otherwise DatasetError naming the argument."""
    _check_map_settings(size, crop_mm, y_far_m)
    if not (_whole(oversample) and 1 <= oversample <= MAX_OVERSAMPLE):
        raise DatasetError(f"oversample must be an integer in [1, {MAX_OVERSAMPLE}], got {oversample!r}")
    n = size * oversample
    centres = (np.arange(n) + 0.5) * (crop_mm / n) - crop_mm / 2
    z, x = np.meshgrid(centres, centres, indexing="ij")
    y_m = surface(x, z).reshape(size, oversample, size, oversample).min(axis=(1, 3)) * 1e-3
    return np.minimum(y_m, y_far_m).astype(np.float32)


def analytic_contact_maps(count: int, seed: int, y_far_m: float, size: int = 100, crop_mm: float = 24.0) -> np.ndarray:
    """count x size x size float32 depth-maps (m) of random analytic contacts, every shape of
    :data:`SHAPES` in turn. ``count`` an integer >= 0 (none: no maps), ``size`` in
    [1, MAX_CONTACT_MAP_SIZE], count x size² at most MAX_CONTACT_MAP_BINS, ``crop_mm`` in
    (0, MAX_CROP_MM], ``y_far_m`` finite; otherwise DatasetError naming the argument."""
    _check_map_settings(size, crop_mm, y_far_m)
    if not (_whole(count) and count >= 0):
        raise DatasetError(f"count must be an integer >= 0, got {count!r}")
    if count * size * size > MAX_CONTACT_MAP_BINS:
        raise DatasetError(f"count x size² = {count * size * size} bins, more than {MAX_CONTACT_MAP_BINS}")
    rng = np.random.default_rng(seed)
    maps = np.empty((count, size, size), np.float32)
    for i, depth_map in enumerate(maps):
        depth_map[...] = depth_map_from_surface(random_surface(SHAPES[i % len(SHAPES)], rng), size, crop_mm, y_far_m)
    return maps


# Bounds of the analytic maps: the network's maps are 100 or 256 bins a side, and a map is sampled
# up to 4 x 4 per bin in float64 (a 512-bin map: 32 MB a working array); 2**26 bins are 256 MiB
# of maps; a crop of 100 mm is four gels across.
MAX_CONTACT_MAP_SIZE = 512
MAX_OVERSAMPLE = 4
MAX_CONTACT_MAP_BINS = 2**26
MAX_CROP_MM = 100.0


def _check_map_settings(size: int, crop_mm: float, y_far_m: float) -> None:
    """DatasetError naming the argument unless ``size`` is an integer in [1, MAX_CONTACT_MAP_SIZE],
    ``crop_mm`` in (0, MAX_CROP_MM] and ``y_far_m`` finite."""
    if not (_whole(size) and 1 <= size <= MAX_CONTACT_MAP_SIZE):
        raise DatasetError(f"size must be an integer in [1, {MAX_CONTACT_MAP_SIZE}], got {size!r}")
    if not (0 < crop_mm <= MAX_CROP_MM and abs(y_far_m) < np.inf):
        raise DatasetError(f"crop_mm must be in (0, {MAX_CROP_MM:g}] and y_far_m finite, got {crop_mm!r}, {y_far_m!r}")


def _whole(value: object) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def gel_gap_from_surface(
    surface: SurfaceMm, height: int, width: int, pixel_pitch_mm: tuple[float, float]
) -> np.ndarray:
    """height x width gel gap in mm at the tactile pixel centres (+inf = nothing there);
    ``pixel_pitch_mm`` is (between rows, between columns)."""
    rows = (np.arange(height) + 0.5 - height / 2) * pixel_pitch_mm[0]
    cols = (np.arange(width) + 0.5 - width / 2) * pixel_pitch_mm[1]
    z, x = np.meshgrid(rows, cols, indexing="ij")
    return surface(x, z).astype(np.float32)


# The real GelSight camera frame: 160 columns of 0.1245 mm (assets/gelsight).
CAMERA_FIELD_WIDTH_MM = 160 * 0.1245


def gelsight_renderer(size: int) -> tuple[TactileRenderer, tuple[float, float]]:
    """The simulated GelSight at size x size pixels showing the whole camera field, and its
    pixel pitch (between rows, between columns) in mm."""
    try:
        from sim.gelsight import GelSightConfig, GelSightRenderer  # noqa: PLC0415 (other part)
    except ImportError as err:
        raise DatasetError(f"the synthetic dataset needs sim.gelsight.GelSightRenderer ({err})") from err
    renderer = GelSightRenderer(
        GelSightConfig(image_height=size, image_width=size, mm_per_px=CAMERA_FIELD_WIDTH_MM / size)
    )
    return renderer, tuple(float(p) for p in renderer.pixel_pitch_mm)  # type: ignore[return-value]


def write_synthetic_dataset(
    out: str | os.PathLike[str],
    samples: int,
    seed: int,
    renderer: TactileRenderer | None = None,
    pixel_pitch_mm: tuple[float, float] = (0.0, 0.0),
    crop_scale: float = 1.2,
    depth_range_m: tuple[float, float] = (-0.0015, 0.0025),
    progress: bool = False,
) -> DatasetWriter:
    """Write ``samples`` 100 x 100 samples to ``out``, two fingers per grasp. Resumes:
    samples already present are regenerated identically and skipped. Without ``renderer``
    the simulated GelSight renders the images (``pixel_pitch_mm`` is then its own)."""
    if samples <= 0:
        raise DatasetError(f"--samples must be positive, got {samples}")
    size = 100
    if renderer is None:
        renderer, pixel_pitch_mm = gelsight_renderer(size)
    if not min(pixel_pitch_mm) > 0:
        raise DatasetError(f"pixel_pitch_mm must be positive, got {pixel_pitch_mm}")
    _check_map_settings(size, size * pixel_pitch_mm[1] * crop_scale, depth_range_m[1])  # before anything is written
    background = renderer.render(np.full((size, size), np.inf, np.float32))
    writer = DatasetWriter(out, _synthetic_info(size, seed, crop_scale, depth_range_m))
    n_grasps = (samples + 1) // 2
    for grasp_id in track(range(n_grasps), "synthetic grasps", "grasps", enabled=progress):
        # One generator per grasp: a resumed run draws exactly the same grasps.
        rng = np.random.default_rng([seed, grasp_id])
        shape = SHAPES[int(rng.integers(len(SHAPES)))]
        pose = _random_grasp_pose(rng)
        for finger in ("left", "right")[: min(2, samples - 2 * grasp_id)]:
            surface = random_surface(shape, rng)
            sample_id = f"{shape}-g{grasp_id:05d}-{finger}"
            if sample_id in writer:
                continue
            tactile = renderer.render(gel_gap_from_surface(surface, size, size, pixel_pitch_mm))
            writer.write(
                sample_id=sample_id,
                object_name=shape,
                grasp_id=grasp_id,
                finger=finger,
                grasp_pose=pose,
                tactile_rgb=tactile,
                tactile_diff_rgb=subtract_background(tactile, background),
                depth_map_m=depth_map_from_surface(
                    surface, size, size * pixel_pitch_mm[1] * crop_scale, depth_range_m[1]
                ),
                registration_fitness=1.0,
            )
    return writer


def _synthetic_info(size: int, seed: int, crop_scale: float, depth_range_m: tuple[float, float]) -> DatasetInfo:
    """The synthetic dataset's ``dataset.json``: its scene names the seed and the crop scale."""
    return DatasetInfo(
        image_height=size,
        image_width=size,
        depth_range_m=depth_range_m,
        scene=f"synthetic analytic contacts (seed {seed}, crop x{crop_scale})",
        effects=(),
        code_version=code_version(),
        split_seed=seed,
    )


def _random_grasp_pose(rng: np.random.Generator) -> tuple[float, float, float, float]:
    """A grasp pose (x, y, z [m], theta_z [rad]) over the table, as a sample records it."""
    return (
        float(rng.uniform(-0.05, 0.05)),
        float(rng.uniform(-0.05, 0.05)),
        float(rng.uniform(0.05, 0.15)),
        float(rng.uniform(-np.pi, np.pi)),
    )
