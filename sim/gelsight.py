"""GelSight renderer: from what touches the gel to the RGB image the sensor's camera sees.

Input is the gel gap map (HxW float mm, gel frame of ``workcell.kinematics``): per pixel, the
y of the object's surface, negative where the object reaches into the gel, +inf where there
is nothing. The image is made in four steps, all in mm and pixels:

1. Indentation: how far the object reaches past the gel's rest surface, ``max(-gap, 0)``.
2. Gel deformation: the elastomer does not follow the object only where it touches; it is
   dragged down around the contact too. The gel's response to the indentation is modelled as
   a smooth elastic spread (a Gaussian of width ``spreading_length_mm``: a thin layer bonded
   to rigid acrylic responds within about its thickness), and where the object is deeper
   than that response the gel lies on the object (contact re-imposed):
   ``max(indentation, spread)``. A small optical blur follows (the camera does not resolve
   finer).
3. Shading with the real calibration (Taxim, assets/gelsight/ATTRIBUTION.md): the surface
   slope is binned by magnitude ``atan|grad h|`` and direction ``atan2``, and each bin's
   polynomial in pixel position gives the colour change (the table is interpolated between
   bin centres, ``sim.gelsight_calibration``). Two physical corrections, fitted on
   real frames: the pressed gel also changes colour where it is flat (the calibration's
   zero-slope colour, applied in proportion to the local compression up to
   ``compression_saturation_mm``), and a global ``shading_gain``.
4. Background: the sensor's no-contact frame, smoothed (``background_smoothing_mm``) because
   the camera's fringe pattern changes from frame to frame and is not predictable from the
   contact, so its expectation is the smooth frame.

The calibration was made on 120x160 images at ``calibration_mm_per_px``; other image sizes
map each pixel to its position on the gel and evaluate the calibration there.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import cv2
import numpy as np

from sim.effects import effects_of, resolve_effects
from sim.gelsight_calibration import PolyCalibration, load_calibration, renderer_parameters
from sim.gelsight_effects import EFFECTS, GelSightRenderError, LightingDrift, Markers, SensorNoise, make_effect
from sim.gelsight_shading import colour_change, slope_bin_edges
from workcell.scene import Scene

__all__ = [
    "EFFECTS",
    "GelSightConfig",
    "GelSightRenderError",
    "GelSightRenderer",
    "LightingDrift",
    "Markers",
    "SensorNoise",
    "gel_surface_depth_mm",
    "indentation_mm",
    "make_effect",
    "render_depth_maps",
    "scene_renderer",
]

# Coarse-grid points per spreading sigma when the spread is computed on a coarser grid.
SPREAD_GRID_PER_SIGMA = 3.0
# Working-grid points per optical blur sigma (see GelSightRenderer).
SHADING_GRID_PER_SIGMA = 3.0
# Bounds that keep every Gaussian kernel OpenCV builds small (its width is ~8 sigma): lengths on
# the gel up to 50 mm (a GelSight gel is ~25 mm across), pixel pitches 1 um..10 mm (the real
# field at 3..4096 px wide is 6.6..0.005 mm/px), and the background's smoothing at most 256
# calibration pixels (the calibration frame is 160 wide: more is its mean).
MAX_LENGTH_MM = 50.0
PIXEL_PITCH_RANGE_MM = (1e-3, 10.0)
MAX_BACKGROUND_SIGMA_PX = 256.0


@dataclasses.dataclass(frozen=True)
class GelSightConfig:
    """Image size, scale and the renderer's physical parameters.

    ``mm_per_px`` is the pixel pitch along the image width; the image is centred on the gel
    and always shows a field of view of the calibration frame's shape (4:3), so it is
    ``image_width * mm_per_px`` wide and 3/4 of that high. At the 4:3 sizes (120x160,
    480x640) pixels are square; a 100x100 image (the learning size) is the camera's field
    resampled, as the paper resized its GelSight frames, so its rows are 0.75 * mm_per_px
    apart (:attr:`GelSightRenderer.pixel_pitch_mm` gives both pitches).

    The five parameters after ``elastomer_thickness_mm`` were fitted on the even frames of
    the 30 real ball presses in assets/gelsight/ball_presses.npz, by maximising mean crop +
    full-frame SSIM from neutral start values (``sim.gelsight_check.fit_parameters``), and
    rounded to 0.01; the odd frames, not used in the fit, score within 0.005 of the even ones
    (``dtx sim gelsight-check --holdout``).

    Contract, checked on construction (GelSightRenderError names the field): sizes are integers in
    [3, 4096]; every length a finite number in (0, MAX_LENGTH_MM] mm; both pixel pitches in
    PIXEL_PITCH_RANGE_MM; ``background_smoothing_mm / calibration_mm_per_px`` at most
    MAX_BACKGROUND_SIGMA_PX; ``shading_gain`` in [0, 2]. Within these a rendering takes bounded
    time and memory (the largest image, 4096 x 4096, ~1 GB).
    """

    image_height: int = 120
    image_width: int = 160
    mm_per_px: float = 0.1245
    calibration_dir: str = "assets/gelsight"
    calibration_mm_per_px: float = 0.1245  # pixel pitch of the calibration images
    # The rigid acrylic under the gel stops any indentation deeper than this.
    elastomer_thickness_mm: float = 3.0
    spreading_length_mm: float = 0.68  # sigma of the gel's elastic spread around a contact
    optical_blur_mm: float = 0.20  # sigma of what the camera cannot resolve
    compression_saturation_mm: float = 0.94  # press depth at which flat-gel colour change is full
    shading_gain: float = 0.93  # scale of all colour changes from the contact
    background_smoothing_mm: float = 0.80  # sigma of the no-contact frame's smoothing

    def __post_init__(self) -> None:
        for name in ("image_height", "image_width"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or not 3 <= value <= 4096:
                raise GelSightRenderError(f"GelSightConfig.{name} must be an integer in [3, 4096], got {value!r}")
        pitches = ("mm_per_px", "calibration_mm_per_px")
        lengths = (
            "elastomer_thickness_mm",
            "spreading_length_mm",
            "optical_blur_mm",
            "compression_saturation_mm",
            "background_smoothing_mm",
        )
        for name in pitches + lengths + ("shading_gain",):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise GelSightRenderError(f"GelSightConfig.{name} must be a finite number, got {value!r}")
        for name in lengths:
            if not 0 < getattr(self, name) <= MAX_LENGTH_MM:
                raise GelSightRenderError(
                    f"GelSightConfig.{name} must be in (0, {MAX_LENGTH_MM}] mm, got {getattr(self, name)!r}"
                )
        for name in pitches:
            low, high = PIXEL_PITCH_RANGE_MM
            if not low <= getattr(self, name) <= high:
                raise GelSightRenderError(
                    f"GelSightConfig.{name} must be in [{low}, {high}] mm per pixel, got {getattr(self, name)!r}"
                )
        if self.background_smoothing_mm / self.calibration_mm_per_px > MAX_BACKGROUND_SIGMA_PX:
            raise GelSightRenderError(
                f"GelSightConfig.background_smoothing_mm {self.background_smoothing_mm!r} is "
                f"{self.background_smoothing_mm / self.calibration_mm_per_px:.3g} calibration "
                f"pixels, more than {MAX_BACKGROUND_SIGMA_PX:g}"
            )
        if not 0.0 <= self.shading_gain <= 2.0:
            raise GelSightRenderError(f"GelSightConfig.shading_gain must be in [0, 2], got {self.shading_gain!r}")

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.image_height), int(self.image_width)


def indentation_mm(gel_gap_mm: np.ndarray, max_mm: float) -> np.ndarray:
    """How far the object reaches past the gel's rest surface (HxW float32 mm, >= 0),
    limited to ``max_mm`` (the elastomer's thickness: the acrylic under it is rigid)."""
    if not isinstance(gel_gap_mm, np.ndarray):
        raise GelSightRenderError(f"gel gap map must be a numpy array, got {type(gel_gap_mm).__name__}")
    if gel_gap_mm.ndim != 2 or min(gel_gap_mm.shape) < 3:
        raise GelSightRenderError(f"gel gap map must be HxW with H, W >= 3, got shape {gel_gap_mm.shape}")
    if not np.issubdtype(gel_gap_mm.dtype, np.floating):
        raise GelSightRenderError(f"gel gap map must be float (mm, +inf = nothing there), got {gel_gap_mm.dtype}")
    if np.isnan(gel_gap_mm).any():
        raise GelSightRenderError("gel gap map contains NaN (use +inf where nothing is there)")
    if np.isneginf(gel_gap_mm).any():
        raise GelSightRenderError("gel gap map contains -inf: an object cannot reach infinitely deep")
    # -(+inf) = -inf, so "nothing there" becomes zero indentation without a special case.
    return np.clip(-gel_gap_mm, 0.0, max_mm).astype(np.float32)


def spread_coarsening(spreading_sigma_px: tuple[float, float]) -> int:
    """How many times coarser than the image the elastic spread is computed (1: on the image).
    The spread is smooth on its own length, so on large images it is computed on a grid a few
    times coarser than that length and interpolated back: the same field, far cheaper."""
    return max(1, int(min(spreading_sigma_px) // SPREAD_GRID_PER_SIGMA))


def gel_surface_depth_mm(
    indentation: np.ndarray, spreading_sigma_px: tuple[float, float], blur_sigma_px: tuple[float, float]
) -> np.ndarray:
    """Depth (mm, >= 0) of the deformed gel surface below its rest plane.

    The elastic spread of the indentation, with the contact re-imposed where the object is
    deeper than the spread (the gel cannot pass through the object), then the optical blur.
    Sigmas are in pixels, (along rows, along columns).
    """
    h, w = indentation.shape
    coarsening = spread_coarsening(spreading_sigma_px)
    if coarsening > 1:
        coarse = cv2.resize(
            indentation, (max(1, w // coarsening), max(1, h // coarsening)), interpolation=cv2.INTER_AREA
        )
        spread = _gaussian_blur(
            coarse, (spreading_sigma_px[0] * coarse.shape[0] / h, spreading_sigma_px[1] * coarse.shape[1] / w)
        )
        spread = cv2.resize(spread, (w, h), interpolation=cv2.INTER_LINEAR)
    else:
        spread = _gaussian_blur(indentation, spreading_sigma_px)
    return _gaussian_blur(np.maximum(indentation, spread), blur_sigma_px)


def _gaussian_blur(image: np.ndarray, sigma_px: tuple[float, float]) -> np.ndarray:
    """Gaussian blur with sigma (along rows, along columns) in pixels; the gel continues
    beyond the image edge as it is at the edge."""
    return cv2.GaussianBlur(image, (0, 0), sigmaX=sigma_px[1], sigmaY=sigma_px[0], borderType=cv2.BORDER_REPLICATE)


@dataclasses.dataclass(frozen=True)
class ShadingGrid:
    """The working grid a renderer shades on and what it computed once for it, read-only (the
    arrays too): other drawings of the same images (models.prior_tensor) read it from here."""

    shape: tuple[int, int]  # rows, cols
    pitch_mm: tuple[float, float]  # along rows, along columns
    spread_px: tuple[float, float]  # the elastic spread's sigma, working pixels
    blur_px: tuple[float, float]  # the optical blur's sigma, working pixels
    terms: np.ndarray  # the calibration polynomial's position terms, pixels x 6
    coeffs: np.ndarray  # its coefficients per slope bin, n_bins² x 3 x 6, magnitude-major
    n_bins: int
    flat_colour: np.ndarray  # the flat pressed gel's colour (the zero-slope bin), pixels x 3
    flat_change: np.ndarray  # its full colour change, times the shading gain: rows x cols x 3
    mag_step: float  # a magnitude bin's width, rad of atan(slope)
    dir_step: float  # a direction bin's width, rad
    tilted_tan: np.float32  # below this slope a pixel takes the zero-slope bin: no tilt colour
    tan_edges: np.ndarray  # the magnitude bins' edges as slopes, n_bins + 1 (sim.gelsight_shading)
    direction_edges: np.ndarray  # the direction bins' edges as unit vectors, 2 x (n_bins + 1)


class GelSightRenderer:
    """Renders gel gap maps into GelSight images at ``config``'s size.

    ``effects`` (from :mod:`sim.gelsight_effects`) are applied in order; with none the image
    is the noise-free rendering, deterministic. ``rng`` drives the effects (default: seeded
    with 0, so a run is reproducible). ``background`` is the sensor's no-contact frame at the
    calibration's size or at the image's (default: the calibration's own); render against the
    background captured at start. ``calibration`` shades instead of ``config.calibration_dir``'s (a fit's
    calibration before it is written, ``sim.gelsight_fit``).

    The camera does not resolve the gel finer than ``optical_blur_mm``, so on large images
    (480x640) the deformation and the colour change are computed on a coarser working grid
    (:data:`SHADING_GRID_PER_SIGMA` points per blur sigma) and interpolated to the image; the
    background keeps the image's full resolution.
    """

    def __init__(
        self,
        config: GelSightConfig = GelSightConfig(),
        effects: Sequence = (),
        rng: np.random.Generator | None = None,
        background: np.ndarray | None = None,
        calibration: PolyCalibration | None = None,
    ):
        if not isinstance(config, GelSightConfig):
            raise GelSightRenderError(f"config must be a GelSightConfig, got {type(config).__name__}")
        for effect in effects:
            if not callable(getattr(effect, "apply", None)):
                raise GelSightRenderError(f"effect {effect!r} has no apply(image, gel_depth_mm, pixel_pitch_mm, rng)")
        self.config = config
        self.effects = tuple(effects)
        self.rng = np.random.default_rng(0) if rng is None else rng
        self.calibration = load_calibration(config.calibration_dir) if calibration is None else calibration
        native = self.calibration.native_shape
        background = self.calibration.background if background is None else background
        sizes = (native + (3,), config.shape + (3,))
        if not (isinstance(background, np.ndarray) and background.dtype == np.uint8 and background.shape in sizes):
            raise GelSightRenderError(
                f"background must be a uint8 frame of the calibration's size or the image's, {' or '.join(map(str, sizes))}"
                f", got {getattr(background, 'shape', None)} {getattr(background, 'dtype', None)}"
            )
        h, w = config.shape
        row_mm = config.mm_per_px * (w / h) * (native[0] / native[1])
        self.pixel_pitch_mm = (row_mm, config.mm_per_px)  # along rows, along columns
        coarsening = max(1, int(config.optical_blur_mm / max(self.pixel_pitch_mm) // SHADING_GRID_PER_SIGMA))
        work_shape = (max(3, round(h / coarsening)), max(3, round(w / coarsening)))
        self.grid = self._shading_grid(work_shape, (row_mm * h / work_shape[0], config.mm_per_px * w / work_shape[1]))
        self.background_levels = self._smoothed_background(background)  # ``background`` rounds it
        self.background_levels.flags.writeable = False

    def _smoothed_background(self, frame: np.ndarray) -> np.ndarray:
        """``frame`` smoothed by ``background_smoothing_mm`` at the image's size (float32 levels):
        a frame of the calibration's size is resampled at the image's pixels; a frame of the
        image's size is the rendered camera's own (a press file's background at any size)."""
        config, smoothing_mm = self.config, self.config.background_smoothing_mm
        if frame.shape[:2] != self.calibration.native_shape:
            row_mm, column_mm = self.pixel_pitch_mm
            return _gaussian_blur(frame.astype(np.float32), (smoothing_mm / row_mm, smoothing_mm / column_mm))
        sigma_px = smoothing_mm / config.calibration_mm_per_px
        smoothed = _gaussian_blur(frame.astype(np.float32), (sigma_px, sigma_px))
        xx, yy = self._calibration_positions(config.shape, self.pixel_pitch_mm)
        return cv2.remap(smoothed, xx, yy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def _shading_grid(self, shape: tuple[int, int], pitch_mm: tuple[float, float]) -> ShadingGrid:
        config, n = self.config, self.calibration.n_bins
        xx, yy = self._calibration_positions(shape, pitch_mm)
        # The polynomial terms depend only on pixel position: computed once per size.
        terms = np.stack([xx * xx, yy * yy, xx * yy, xx, yy, np.ones_like(xx)], axis=-1).reshape(-1, 6)
        # The flat pressed gel's colour at each working pixel: fully pressed it adds shading_gain times this.
        flat_colour = terms @ self.calibration.coeffs[0, 0].T
        tan_edges, direction_edges = slope_bin_edges(n)
        grid = ShadingGrid(
            shape=shape,
            pitch_mm=pitch_mm,
            spread_px=(config.spreading_length_mm / pitch_mm[0], config.spreading_length_mm / pitch_mm[1]),
            blur_px=(config.optical_blur_mm / pitch_mm[0], config.optical_blur_mm / pitch_mm[1]),
            terms=terms,
            coeffs=self.calibration.coeffs.reshape(n * n, 3, 6).copy(),
            n_bins=n,
            flat_colour=flat_colour,
            flat_change=np.float32(config.shading_gain) * flat_colour.reshape(*shape, 3),
            mag_step=0.5 * math.pi / n,
            dir_step=2.0 * math.pi / n,
            tilted_tan=np.float32(tan_edges[1]),  # the first magnitude bin's far edge
            tan_edges=tan_edges,
            direction_edges=direction_edges,
        )
        for array in (grid.terms, grid.coeffs, grid.flat_colour, grid.flat_change, tan_edges, direction_edges):
            array.flags.writeable = False
        return grid

    def _calibration_positions(self, shape: tuple[int, int], pitch_mm: tuple[float, float]):
        """Positions (x column, y row; float32 grids) in the calibration image of the pixel
        centres of a grid of ``shape`` and ``pitch_mm``, centred on the gel."""
        native = self.calibration.native_shape
        to_native = [p / self.config.calibration_mm_per_px for p in pitch_mm]
        y = (np.arange(shape[0]) - (shape[0] - 1) / 2.0) * to_native[0] + (native[0] - 1) / 2.0
        x = (np.arange(shape[1]) - (shape[1] - 1) / 2.0) * to_native[1] + (native[1] - 1) / 2.0
        xx, yy = np.meshgrid(x.astype(np.float32), y.astype(np.float32))
        return xx, yy

    def background(self) -> np.ndarray:
        """The image of the untouched gel (HxWx3 uint8): what ``render`` gives for nothing there."""
        return _to_uint8(self.background_levels.copy())

    def gel_depth_mm(self, gel_gap_mm: np.ndarray) -> np.ndarray:
        """The deformed gel surface (HxW float32 mm below rest, image size) for a gap map.

        A gap map of another size is taken to cover the image's field of view and is
        resampled (area-averaged when shrinking, bilinear when enlarging).
        """
        return self._to_image_size(self._work_depth(gel_gap_mm))

    def render(self, gel_gap_mm: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """The GelSight image (HxWx3 uint8 RGB) of a gel gap map (mm; < 0 pressing, +inf none);
        the effects draw from ``rng`` (default: the renderer's own stream)."""
        rng = self.rng if rng is None else rng
        depth = self._work_depth(gel_gap_mm)
        image = self.background_levels + self._to_image_size(self._colour_change(depth))
        gel_depth = self._to_image_size(depth) if self.effects else None
        for effect in self.effects:
            image = effect.apply(image, gel_depth, self.pixel_pitch_mm, rng)
        return _to_uint8(image)

    def _work_depth(self, gel_gap_mm: np.ndarray) -> np.ndarray:
        """The deformed gel surface on the working grid."""
        indentation = indentation_mm(gel_gap_mm, self.config.elastomer_thickness_mm)
        h, w = self.grid.shape
        if indentation.shape != (h, w):
            shrink = indentation.shape[0] > h or indentation.shape[1] > w
            indentation = cv2.resize(indentation, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
        return gel_surface_depth_mm(indentation, self.grid.spread_px, self.grid.blur_px)

    def _to_image_size(self, grid: np.ndarray) -> np.ndarray:
        h, w = self.config.shape
        if grid.shape[:2] == (h, w):
            return grid
        return cv2.resize(grid, (w, h), interpolation=cv2.INTER_LINEAR)

    def _colour_change(self, depth: np.ndarray) -> np.ndarray:
        """Colour change (float32 levels, working grid x 3) of the gel surface ``depth`` (mm), by
        sim.gelsight_shading; slopes in mm per mm, as the calibration's in pixels per pixel."""
        grid, config = self.grid, self.config
        row_mm, col_mm = grid.pitch_mm
        return colour_change(
            np.ascontiguousarray(depth, np.float32),
            (np.float32(0.5 / col_mm), np.float32(0.5 / row_mm)),
            grid.flat_change,
            np.float32(1.0 / config.compression_saturation_mm),
            grid.tilted_tan,
            grid.tan_edges,
            grid.direction_edges,
            grid.coeffs,
            grid.terms,
            grid.flat_colour,
            np.float32(config.shading_gain),
        )


def scene_renderer(
    scene: Scene, size: tuple[int, int] | None = None, effects: bool = True, rng: np.random.Generator | None = None
) -> GelSightRenderer:
    """The GelSight a scene describes: its gel and field of view, at its image size or at
    ``size`` (rows, columns; the same field in more or fewer pixels), its calibration directory
    with the physical parameters fitted there (``dtx calibrate gelsight``), with the GelSight
    effects the scene calls for unless ``effects`` is False."""
    gs = scene.gelsight
    h, w = size or (gs.image_height, gs.image_width)
    config = GelSightConfig(
        image_height=h,
        image_width=w,
        mm_per_px=gs.mm_per_px * gs.image_width / w,
        calibration_dir=gs.calibration_dir,
        elastomer_thickness_mm=scene.gripper.elastomer_thickness_m * 1e3,
        **renderer_parameters(gs.calibration_dir),
    )
    called_for = (
        [make_effect(e.name, e.params) for e in effects_of(resolve_effects(scene), "gelsight")] if effects else []
    )
    return GelSightRenderer(config, effects=called_for, rng=rng)


# Most pixels one call of render_depth_maps draws (maps x image pixels): 192 MiB of RGB. A
# planner's request is at most a few hundred maps and an evaluation split a few thousand at the
# GelSight's 120 x 160 (19 200 px each).
MAX_RENDERED_PIXELS = 2**26
# Most bins of one depth-map: as many as the largest image the renderer draws (4096 x 4096); a
# map's float32 gap copy is then at most 64 MiB.
MAX_MAP_BINS = 4096 * 4096
# Gaps beyond this (mm, either way) render as this: the gel, at most MAX_LENGTH_MM thick, is
# untouched by anything farther and fully pressed by anything deeper.
GAP_LIMIT_MM = 1e3


def checked_depth_maps(
    renderer: GelSightRenderer, depth_maps_m: np.ndarray, crop_xz_m: tuple[float, float]
) -> np.ndarray:
    """``depth_maps_m`` as an array when render_depth_maps can draw them with ``renderer`` over
    ``crop_xz_m`` (its contract); GelSightRenderError naming the argument otherwise."""
    maps = np.asarray(depth_maps_m)
    if maps.ndim != 3 or maps.dtype.kind != "f":
        raise GelSightRenderError(
            f"depth_maps_m must be an N x rows x cols float array in metres, got {maps.shape} {maps.dtype}"
        )
    count, rows, cols = maps.shape
    h, w = renderer.config.shape
    if not 1 <= rows * cols <= MAX_MAP_BINS:
        raise GelSightRenderError(f"depth_maps_m must have 1 to {MAX_MAP_BINS} bins a map, got {rows} x {cols}")
    if count * h * w > MAX_RENDERED_PIXELS:
        raise GelSightRenderError(
            f"depth_maps_m: {count} maps of {h} x {w} px are more than {MAX_RENDERED_PIXELS} pixels a call"
        )
    if np.isneginf(maps).any():
        raise GelSightRenderError("depth_maps_m contains -inf: an object cannot reach infinitely deep")
    crop = np.asarray(crop_xz_m, dtype=np.float64) if np.ndim(crop_xz_m) == 1 else np.array([np.nan])
    if crop.shape != (2,) or not np.all((crop > 0) & (crop < np.inf)):
        raise GelSightRenderError(f"crop_xz_m must be two finite positive extents in m, got {crop_xz_m!r}")
    pitch_rows_mm, pitch_cols_mm = renderer.pixel_pitch_mm
    crop_x_mm, crop_z_mm = crop[0] * 1e3, crop[1] * 1e3
    if w * pitch_cols_mm > crop_x_mm + 1e-6 or h * pitch_rows_mm > crop_z_mm + 1e-6:
        raise GelSightRenderError(
            f"the depth-maps' crop ({crop_x_mm:.1f} x {crop_z_mm:.1f} mm) is smaller than the "
            f"GelSight's field of view ({w * pitch_cols_mm:.1f} x {h * pitch_rows_mm:.1f} mm)"
        )
    return maps


def camera_pixels_on_map(
    renderer: GelSightRenderer, map_shape: tuple[int, int], crop_xz_m: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Where the camera's pixel centres fall on a depth-map of ``map_shape`` (rows, cols) over a
    crop of ``crop_xz_m`` centred on the gel: H x W float32 column and row coordinates in bins
    (bin centres at integers), as cv2.remap takes them."""
    rows, cols = map_shape
    h, w = renderer.config.shape
    pitch_rows_mm, pitch_cols_mm = renderer.pixel_pitch_mm
    crop_x_mm, crop_z_mm = np.asarray(crop_xz_m, dtype=np.float64) * 1e3
    u = ((np.arange(w) - (w - 1) / 2) * pitch_cols_mm + crop_x_mm / 2) / crop_x_mm * cols - 0.5
    v = ((np.arange(h) - (h - 1) / 2) * pitch_rows_mm + crop_z_mm / 2) / crop_z_mm * rows - 0.5
    map_u, map_v = np.meshgrid(u.astype(np.float32), v.astype(np.float32))
    return map_u, map_v


def render_depth_maps(
    renderer: GelSightRenderer, depth_maps_m: np.ndarray, crop_xz_m: tuple[float, float]
) -> np.ndarray:
    """The renderer's image (N x H x W x 3 uint8, its own size) of each contact depth-map, read
    as the gel gap: N x rows x cols maps in the gel frame (m; rows along gel z, columns along gel
    x; perception.depthmap) over a crop of ``crop_xz_m`` (x, z extents) centred on the gel,
    resampled at the renderer's pixel centres (bilinear; edge bins repeat). This is physics fed
    exactly what a learned model is fed; the crop must cover the renderer's field of view.

    Contract: ``depth_maps_m`` a real float array, N >= 0 maps (none: no images) of at least
    one bin and at most MAX_MAP_BINS; values finite, +inf or NaN (both: nothing there),
    gaps beyond GAP_LIMIT_MM either way read as that limit; N x H x W at most
    MAX_RENDERED_PIXELS; ``crop_xz_m`` two finite positive extents. Otherwise GelSightRenderError
    naming the argument, before anything is drawn."""
    maps = checked_depth_maps(renderer, depth_maps_m, crop_xz_m)
    count, rows, cols = maps.shape
    map_u, map_v = camera_pixels_on_map(renderer, (rows, cols), crop_xz_m)
    images = np.empty((count, *renderer.config.shape, 3), np.uint8)
    for image, depth_map_m in zip(images, maps):
        # Clipped in the input's dtype before the mm scale and the float32 cast, which would overflow.
        gap_mm = np.clip(np.nan_to_num(depth_map_m, nan=np.inf), -GAP_LIMIT_MM * 1e-3, GAP_LIMIT_MM * 1e-3)
        gap_mm = gap_mm.astype(np.float32) * np.float32(1e3)
        image[...] = renderer.render(cv2.remap(gap_mm, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
    return images


def _to_uint8(image: np.ndarray) -> np.ndarray:
    """Rounds to 8-bit levels, saturating; overwrites ``image``."""
    np.clip(image, 0.0, 255.0, out=image)
    return np.rint(image, out=image).astype(np.uint8)
