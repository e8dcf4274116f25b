"""Contact depth-maps: the registered model cloud seen from one gel (paper §III-B.3).

Gel frame (see workcell.kinematics): origin at the centre of the gel surface, x-z in the
surface, y along the outward normal; y > 0 is free space, y < 0 indents the elastomer.

Crop volume: |x| <= sensed_x/2 + margin, |z| <= sensed_z/2 + margin, y_near <= y <= y_far (all
inclusive), where sensed_x, sensed_z is the area of the gel the tactile camera images
(``GripperGeometry.sensed_extent_m``; a GelSight camera sees 19.9 x 14.9 mm of a 18.6 x 24.9 mm
gel), so depth-map and tactile image show the same place at nearly the same scale. The
margin makes the patch larger than the sensor so a learner can absorb the systematic
camera-to-robot calibration offset the paper reports.

Bins: the x-z rectangle is split into ``shape = (rows, cols)`` equal bins, rows along gel z,
columns along gel x — the image a camera would take looking at the gel from the object side
(its optical z along -y, x right, z down). The bin edges are ``linspace(-half, half, n + 1)``
(float64) on each axis; bin i holds [edge_i, edge_i+1), and points on the far crop edge belong
to the last bin, so every cropped point lands in exactly one bin. What a bin holds is
``DepthMapParams.method`` (perception.surface): by default the object's surface at the bin's
centre (a plane through the front-most points of the bin and its neighbours), or the paper's
minimum y of its points (``nearest_point``, configs/paper.yaml).

Empty bins: a bin whose surface is unknown (no points, and none around it that say where the
surface continues; or, nearest_point, no points) holds y_far, the far limit of the crop ("no
surface within reach") — the same value normalisation gives an empty bin, so the map, its
normalised form and the DepthMap message agree. ``occupied`` tells real y_far values from empty
ones. A patch with no point at all has no right answer and raises DepthMapError.

Model density: a 100 x 100 map of a GelSight's sensed area plus 2 mm has 0.24 x 0.19 mm bins,
so the model cloud must be sampled finer than that (MODEL_POINT_SPACING_M, 0.1 mm: ~1 % of bins
left empty and then filled as sampling gaps, where 0.2 mm left a third and the 2 mm
registration cloud fills ~2 %); the paper's 1-80 points/cm³ clouds fill under 6 %.

Precision: model points are moved to the gel frame with one float64 transform composed from
model_to_world and gel_to_world, so a scene far from the world origin loses nothing; float32
points are read as they are (half the memory traffic) and computed with in float64.

Speed: one compiled pass (numba, :mod:`perception.binning`) transforms, crops and bins (~130 M
points/s against ~27 for the same steps in NumPy, ``dtx bench perception --only binning``), then
one compiled pass over the bins for the surface;
:func:`contact_depth_maps` cuts many gels' maps from one indexed cloud, reading only the cells
within each crop's reach.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from perception.binning import bin_edges, cells_meeting_crops, cut_kernel, fill_sampling_gaps, region_groups
from perception.errors import DepthMapError, OutOfReachError
from perception.normalisation import normalise_depth_map
from perception.pointcloud import VoxelIndex, check_transform, check_transforms
from perception.surface import DEPTH_MAP_METHODS, surface_maps
from perception.threads import run_shares
from workcell.kinematics import GripperGeometry

if TYPE_CHECKING:
    import torch

# Spacing of the model cloud depth-maps are made from (``sample_model_cloud``): uniform random
# points at 0.1 mm put ~4.5 in each 0.24 x 0.19 mm bin of a 100 x 100 map of the sensed area,
# leaving ~1 % of bins empty (0.2 mm left a third), which gap filling closes.
MODEL_POINT_SPACING_M = 0.0001
# That cloud is part of the object's model, not of a session's randomness: one seed for all,
# so a dataset's depth-maps can be made again from the mesh (dataset/redepth.py).
MODEL_CLOUD_SEED = 0
# Most bins a depth-map may have: 2048 x 2048 keeps one map's working arrays (float64 minima,
# float32 map and its normalised copy, flags) near 100 MB; the network sees 100 x 100 or 256 x 256.
MAX_DEPTH_MAP_BINS = 2**22


@dataclasses.dataclass(frozen=True)
class DepthMapParams:
    shape: tuple[int, int] = (100, 100)  # (rows along gel z, columns along gel x)
    margin_m: float = 0.002  # added to each side of the gel in x and z
    # Default y range: one elastomer thickness in front of the gel to full indentation behind it.
    y_range_m: tuple[float, float] | None = None  # (y_near, y_far); None: (-t, +t), t = elastomer
    # Nearest-point maps: an empty bin with at least this many occupied neighbours (of 8) is a gap
    # in a sampled surface, not free space: it takes the nearest surface of its neighbours. 0:
    # leave gaps. (Surface maps fill gaps by their own rule, perception.surface.)
    # The default fills the ~10 % of bins a 0.2 mm model cloud leaves empty in 0.2 mm bins, and
    # is what training data and served requests share.
    fill_gaps_min_neighbours: int = 5
    # What a bin holds (perception.surface): "surface", the object's surface at the bin's centre;
    # "nearest_point", the paper's nearest point in the bin (a checkpoint names the one it was
    # trained on, and one trained before names none: nearest_point).
    method: str = "surface"


@dataclasses.dataclass
class ContactPatch:
    depth_map_m: np.ndarray  # (rows, cols) float32, y per bin by params.method, empty bins = y_far
    normalised: np.ndarray  # (rows, cols) float32 in [-1, 1] (perception.normalisation)
    occupied: np.ndarray  # (rows, cols) bool: the surface is known (nearest_point: the bin holds a point)
    crop_m: tuple[float, float, float]  # full crop extent along gel x, y, z
    y_range_m: tuple[float, float]
    point_count: int


def crop_bounds(geometry: GripperGeometry, params: DepthMapParams) -> tuple[float, float, float, float]:
    """(half_x, half_z, y_near, y_far) of the crop volume in metres, validated: every bound
    finite in float32 (the map is stored as float32), positive extent, y_far > y_near, and
    ``params.shape`` two positive Python or NumPy integers with at most MAX_DEPTH_MAP_BINS bins,
    each wider than float32 resolves, gap filling from at most 8 neighbours. Otherwise
    DepthMapError names what is wrong."""
    sensed_x, sensed_z = geometry.sensed_extent_m
    half_x = 0.5 * sensed_x + params.margin_m
    half_z = 0.5 * sensed_z + params.margin_m
    thickness = geometry.elastomer_thickness_m
    y_range = params.y_range_m if params.y_range_m is not None else (-thickness, thickness)
    if not isinstance(y_range, (tuple, list, np.ndarray)) or len(y_range) != 2:
        raise DepthMapError(f"y_range_m must be (y_near, y_far), got {y_range!r}")
    y_near, y_far = y_range
    values = np.array([half_x, half_z, y_near, y_far], dtype=np.float64)
    if not np.all(np.abs(values) <= float(np.finfo(np.float32).max)):  # NaN fails too
        raise DepthMapError(
            f"crop bounds must be finite in float32, got half x {half_x}, half z {half_z}, y {y_near}..{y_far} m"
        )
    if not (half_x > 0 and half_z > 0):
        raise DepthMapError(f"crop must have positive extent, got half x {half_x} m, half z {half_z} m")
    if not y_far > y_near:
        raise DepthMapError(f"depth range must have y_far > y_near, got ({y_near}, {y_far}) m")
    shape = tuple(params.shape) if isinstance(params.shape, (tuple, list)) else ()
    if len(shape) != 2 or not all(
        isinstance(n, (int, np.integer)) and not isinstance(n, bool) and n >= 1 for n in shape
    ):
        raise DepthMapError(f"bin shape must be two positive integers (rows, cols), got {params.shape!r}")
    rows, cols = int(shape[0]), int(shape[1])
    # The map and its crop are stored as float32: bins narrower than float32 can tell apart at
    # the crop edge would alias, so such a map is refused rather than silently merged.
    for half, count, axis in ((half_x, cols, "x"), (half_z, rows, "z")):
        if 2.0 * half / count <= 4 * np.spacing(np.float32(half)):
            raise DepthMapError(
                f"bin size {2.0 * half / count:.3g} m along {axis} is below float32 resolution at {half:.3g} m"
            )
    if not np.float32(y_far) > np.float32(y_near):
        raise DepthMapError(f"depth range ({y_near}, {y_far}) m is below float32 resolution")
    if rows * cols > MAX_DEPTH_MAP_BINS:
        raise DepthMapError(f"bin shape {params.shape} has {rows * cols} bins, more than {MAX_DEPTH_MAP_BINS}")
    if params.fill_gaps_min_neighbours > 8:
        raise DepthMapError(f"min_neighbours must be in 1..8, got {params.fill_gaps_min_neighbours}")
    if params.method not in DEPTH_MAP_METHODS:
        raise DepthMapError(f"depth-map method must be one of {', '.join(DEPTH_MAP_METHODS)}, got {params.method!r}")
    return half_x, half_z, float(y_near), float(y_far)


def crop_reach_m(geometry: GripperGeometry, params: DepthMapParams) -> float:
    """Every model point a gel's depth-map (or the centring between gels) can use lies within
    this distance of the gel centre: the crop's corners, or the gel face's, at the crop's depth."""
    return _reach_m(geometry, crop_bounds(geometry, params))


def _reach_m(geometry: GripperGeometry, bounds: tuple[float, float, float, float]) -> float:
    """:func:`crop_reach_m` from bounds already checked by :func:`crop_bounds`."""
    half_x, half_z, y_near, y_far = bounds
    deepest = max(abs(y_near), abs(y_far))
    return float(
        max(
            np.linalg.norm([half_x, half_z, deepest]),
            np.linalg.norm([0.5 * geometry.gel_size_m[0], 0.5 * geometry.gel_size_m[1], deepest]),
        )
    )


@dataclasses.dataclass
class ContactPatches:
    """N regions' depth-maps, cut from one model cloud in one pass (:func:`contact_depth_maps`)."""

    depth_maps_m: np.ndarray  # (N, rows, cols) float32, as ContactPatch.depth_map_m
    occupied: np.ndarray  # (N, rows, cols) bool, as ContactPatch.occupied
    point_counts: np.ndarray  # (N,) int64, points in each region's crop
    crop_m: tuple[float, float, float]
    y_range_m: tuple[float, float]


def points_for_kernel(points_model_m: np.ndarray) -> np.ndarray:
    """float32 or float64 C-contiguous (N, 3), finite; other bool, integer and float dtypes are used
    in float64. Complex, text and object arrays are no points: DepthMapError."""
    points = np.asarray(points_model_m)
    if points.dtype.kind not in "biuf":
        raise DepthMapError(f"model points must be real numbers (bool, integer or float), got {points.dtype}")
    points = np.ascontiguousarray(points, dtype=points.dtype if points.dtype == np.float32 else np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise DepthMapError(f"model points must be (N, 3), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise DepthMapError("model points must be finite: they contain NaN or inf")
    return points


class _Reads(NamedTuple):
    """The points each region reads, in place: region k the ranges starts[i]:ends[i] of
    ``points`` for the runs i in runs[k]..runs[k+1] (the compiled kernel's layout);
    ``device_points``: the same points on a torch device, to cut there."""

    points: np.ndarray
    starts: np.ndarray
    ends: np.ndarray
    runs: np.ndarray
    device_points: torch.Tensor | None = None


def _min_y_per_region(
    reads: _Reads,
    model_to_gel: np.ndarray,
    bounds: tuple[float, float, float, float],
    shape: tuple[int, int],
    threads: int,
    places: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The kernel's (min_y: regions x bins, +inf where empty; the x and z of each bin's
    front-most point where ``places``, else min_y again; points kept per region), its regions cut
    on up to ``threads`` threads in groups of about equal work."""
    rows, cols = shape
    regions = model_to_gel.shape[0]
    min_y = np.full((regions, rows * cols), np.inf)
    at_x, at_z = (np.zeros_like(min_y), np.zeros_like(min_y)) if places else (min_y, min_y)
    counts = np.zeros(regions, np.int64)
    transforms = np.ascontiguousarray(model_to_gel[:, :3, :], dtype=np.float64)
    crop = np.array(bounds, np.float64)
    x_edges, z_edges = bin_edges(bounds[0], cols), bin_edges(bounds[1], rows)

    def cut_regions(first: int, stop: int) -> None:
        # Region k reads runs runs[k]..runs[k+1] of the whole starts/ends and writes only
        # min_y[k] and counts[k]: a range of regions is cut on its own, in place.
        cut_kernel(
            reads.points,
            reads.starts,
            reads.ends,
            reads.runs[first : stop + 1],
            transforms[first:stop],
            crop,
            x_edges,
            z_edges,
            min_y[first:stop],
            counts[first:stop],
            at_x[first:stop],
            at_z[first:stop],
            places,
        )

    run_shares(cut_regions, region_groups(reads.ends - reads.starts, reads.runs, threads))
    return min_y, at_x, at_z, counts


def _maps(
    reads: _Reads,
    model_to_gel: np.ndarray,
    bounds: tuple[float, float, float, float],
    params: DepthMapParams,
    threads: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth-maps float32 m by ``params.method`` (perception.surface), occupied, points kept
    per region) of every region: the compiled kernel on ``threads`` threads, or the binning on
    the device of ``reads.device_points`` (the same arrays). ``occupied``: the bin holds a point
    (nearest_point), or its surface is known (surface)."""
    shape = (int(params.shape[0]), int(params.shape[1]))
    surface = params.method == "surface"
    fill = max(params.fill_gaps_min_neighbours, 0)  # 0 or less: no gap filling
    if reads.device_points is not None:
        from perception import depthmap_tensor  # noqa: PLC0415 - torch only when asked for

        device_args = (reads.device_points, reads.starts, reads.ends, reads.runs, model_to_gel, bounds, shape)
        if not surface:
            return depthmap_tensor.depth_maps_on_device(*device_args, fill)
        min_y, at_x, at_z, counts = depthmap_tensor.front_points_on_device(*device_args)
    else:
        min_y, at_x, at_z, counts = _min_y_per_region(reads, model_to_gel, bounds, shape, threads, surface)
    min_y = min_y.reshape(-1, *shape)
    if surface:
        depth_maps_m, known = surface_maps(min_y, at_x.reshape(min_y.shape), at_z.reshape(min_y.shape), bounds, threads)
        return depth_maps_m, known, counts
    occupied = np.isfinite(min_y)
    depth_maps_m = np.where(occupied, min_y, bounds[3]).astype(np.float32)
    if fill:
        depth_maps_m = fill_sampling_gaps(depth_maps_m, occupied, fill)
    return depth_maps_m, occupied, counts


def _cut(
    reads: _Reads,
    model_to_gel: np.ndarray,
    bounds: tuple[float, float, float, float],
    params: DepthMapParams,
    batch: bool,
    allow_empty: bool = False,
    threads: int = 1,
    first_region: int = 0,
) -> ContactPatches:
    """The kernel over already checked inputs (``bounds``: :func:`crop_bounds`), on up to
    ``threads`` threads, then the empty-bin policy and gap filling; an error about a region of
    a ``batch`` names it (its regions numbered from ``first_region``). With ``allow_empty`` a
    region with no point is no error: its map is all y_far (point count 0)."""
    half_x, half_z, y_near, y_far = bounds
    depth_maps_m, occupied, counts = _maps(reads, model_to_gel, bounds, params, threads)
    empty = np.flatnonzero(counts == 0)
    if empty.size and not allow_empty:
        raise OutOfReachError(
            f"{f'region {first_region + int(empty[0])}: ' if batch else ''}"
            f"no model point in the contact volume (x ±{half_x * 1e3:.1f} mm, "
            f"z ±{half_z * 1e3:.1f} mm, y {y_near * 1e3:.1f}..{y_far * 1e3:.1f} mm): "
            "the gel does not reach the object"
        )
    return ContactPatches(
        depth_maps_m=depth_maps_m,
        occupied=occupied,
        point_counts=counts,
        crop_m=(2 * half_x, y_far - y_near, 2 * half_z),
        y_range_m=(y_near, y_far),
    )


def surface_bins(depth_maps_m: np.ndarray, y_far_m: float) -> np.ndarray:
    """How many bins of each depth-map (N x H x W, metres) hold a surface: a y below ``y_far_m``,
    compared in float32 as the maps hold it. The others are empty: nothing within the depth range
    there, or a cloud too thin to say where the surface is (perception.surface). (N,) int64."""
    maps = np.asarray(depth_maps_m)
    return np.count_nonzero(maps.reshape(len(maps), -1) < np.float32(y_far_m), axis=1).astype(np.int64)


def _model_to_gels(model_to_world: np.ndarray, gels_to_world: np.ndarray) -> np.ndarray:
    """(N, 4, 4) float64 model-to-gel transforms, each composed in float64, of transforms the
    caller has checked (rigid)."""
    return np.linalg.inv(gels_to_world) @ model_to_world


def contact_depth_map(
    points_model_m: np.ndarray,
    model_to_world: np.ndarray,
    gel_to_world: np.ndarray,
    geometry: GripperGeometry = GripperGeometry(),
    params: DepthMapParams = DepthMapParams(),
) -> ContactPatch:
    """Depth-map of the model cloud (model frame, metres) in the contact volume of one gel.

    ``points_model_m``: finite (N, 3), any real dtype (float32 read as it is, others converted
    to float64; the arithmetic is float64); the transforms rigid
    (perception.pointcloud.check_transform); crop and bins as :func:`crop_bounds`. Anything
    else, or no point in the crop, raises DepthMapError (PointCloudError for a transform).
    Cost: one pass over the points, O(N) time, O(bins) memory beyond a converted copy of the
    points, bins <= MAX_DEPTH_MAP_BINS."""
    bounds = crop_bounds(geometry, params)  # refuses a bad crop or shape before the points are read
    points = points_for_kernel(points_model_m)
    model_to_gel = _model_to_gels(
        check_transform(model_to_world, "model_to_world"), check_transform(gel_to_world, "gel_to_world")[None]
    )
    whole_cloud = _Reads(points, np.array([0], np.int64), np.array([len(points)], np.int64), np.array([0, 1], np.int64))
    patches = _cut(
        whole_cloud,
        model_to_gel,
        bounds,
        params,
        batch=False,
    )
    return ContactPatch(
        depth_map_m=patches.depth_maps_m[0],
        normalised=normalise_depth_map(patches.depth_maps_m[0], patches.y_range_m),
        occupied=patches.occupied[0],
        crop_m=patches.crop_m,
        y_range_m=patches.y_range_m,
        point_count=int(patches.point_counts[0]),
    )


def contact_depth_maps(
    model: VoxelIndex,
    model_to_world: np.ndarray,
    gels_to_world: np.ndarray,
    geometry: GripperGeometry = GripperGeometry(),
    params: DepthMapParams = DepthMapParams(),
    max_point_visits: int | None = None,
    allow_empty: bool = False,
    threads: int = 1,
    device_points: torch.Tensor | None = None,
) -> ContactPatches:
    """Depth-maps of many gels (``gels_to_world``: (N, 4, 4)) on one indexed model cloud: each
    map equals :func:`contact_depth_map` on the whole cloud; :func:`plan_contact_cut` and then
    every region cut (arguments as theirs)."""
    return plan_contact_cut(
        model, model_to_world, gels_to_world, geometry, params, max_point_visits, allow_empty, device_points
    ).cut(threads=threads)


@dataclasses.dataclass(frozen=True)
class PlannedCut:
    """Many gels' depth-maps on one indexed cloud, looked up and bounded (:func:`plan_contact_cut`),
    not yet cut: any run of its regions is cut on its own, with the maps the whole cut gives
    (a planner's request cut pass by pass while the network runs the pass before,
    nodes.inference)."""

    reads: _Reads
    model_to_gel: np.ndarray
    bounds: tuple[float, float, float, float]
    params: DepthMapParams
    allow_empty: bool

    def __len__(self) -> int:
        return len(self.model_to_gel)

    def cut(self, first: int = 0, stop: int | None = None, threads: int = 1) -> ContactPatches:
        """Regions ``first``..``stop`` - 1 (all by default), on up to ``threads`` threads (an
        integer >= 1; never more than regions) in groups of about equal work, or on the device of
        the plan's points; DepthMapError for a run outside the plan or such threads."""
        stop = len(self) if stop is None else stop
        if not (isinstance(threads, (int, np.integer)) and not isinstance(threads, bool) and threads >= 1):
            raise DepthMapError(f"threads must be an integer >= 1, got {threads!r}")
        if not 0 <= first < stop <= len(self):
            raise DepthMapError(f"regions {first}..{stop - 1} are not a run of this cut's {len(self)}")
        runs = self.reads.runs[first : stop + 1]
        starts, ends = self.reads.starts[runs[0] : runs[-1]], self.reads.ends[runs[0] : runs[-1]]
        reads = _Reads(self.reads.points, starts, ends, runs - runs[0], self.reads.device_points)
        return _cut(
            reads, self.model_to_gel[first:stop], self.bounds, self.params, True, self.allow_empty, threads, first
        )


def plan_contact_cut(
    model: VoxelIndex,
    model_to_world: np.ndarray,
    gels_to_world: np.ndarray,
    geometry: GripperGeometry = GripperGeometry(),
    params: DepthMapParams = DepthMapParams(),
    max_point_visits: int | None = None,
    allow_empty: bool = False,
    device_points: torch.Tensor | None = None,
) -> PlannedCut:
    """The cells of ``model`` each gel of ``gels_to_world`` (N, 4, 4) reads, checked and bounded.

    Why batched: a grasp planner asks for tens to hundreds of candidate gel poses on one dense
    cloud (millions of points); the index hands each gel the few cells within its crop's reach
    (:func:`crop_reach_m`), read in place by one compiled pass, instead of every point per gel.
    ``max_point_visits`` bounds the work (points read over all gels, known after the lookups and
    before any is read): more raises DepthMapError. A gel with no point raises DepthMapError
    naming the region when it is cut, unless ``allow_empty``: then its map is all y_far and its
    point count 0 (a planner's candidate that touches nothing is an answer, not a failed batch).
    ``device_points``: ``model.points_m`` on a torch device in their own dtype
    (perception.depthmap_tensor.points_on_device): the maps are cut there, the same maps; another
    shape or dtype raises DepthMapError."""
    bounds = crop_bounds(geometry, params)
    reach = _reach_m(geometry, bounds)
    gels = np.asarray(gels_to_world, dtype=np.float64)
    if gels.ndim != 3 or gels.shape[1:] != (4, 4) or len(gels) == 0:
        raise DepthMapError(f"gel poses must be (N, 4, 4), N >= 1, got shape {gels.shape}")
    if device_points is not None:
        from perception.depthmap_tensor import check_device_points  # noqa: PLC0415 - torch only when asked for

        check_device_points(device_points, model.points_m)
    model_pose = check_transform(model_to_world, "model_to_world")
    model_to_gel = _model_to_gels(model_pose, check_transforms(gels, "gels_to_world"))
    world_to_model = np.linalg.inv(model_pose)
    centres = gels[:, :3, 3] @ world_to_model[:3, :3].T + world_to_model[:3, 3]
    owner, starts, ends, corners = model.cells_within_many(centres, reach)
    meets = cells_meeting_crops(corners, owner, model.cell_m, model_to_gel, bounds)
    owner, starts, ends = owner[meets], starts[meets].astype(np.int64), ends[meets].astype(np.int64)
    runs = np.concatenate([[0], np.cumsum(np.bincount(owner, minlength=len(gels)))]).astype(np.int64)
    visits = int(np.sum(ends - starts))
    if max_point_visits is not None and visits > max_point_visits:
        raise DepthMapError(f"too much work: {visits} model points near {len(gels)} gels > {max_point_visits}")
    reads = _Reads(model.points_m, starts, ends, runs, device_points)
    return PlannedCut(reads, model_to_gel, bounds, params, allow_empty)
