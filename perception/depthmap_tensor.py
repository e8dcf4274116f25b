"""The batched depth-map cut of :func:`perception.depthmap.contact_depth_maps` as tensor
operations on a torch device: transform, crop and minimum y per bin for many gels at once.

Why: on a GPU host the network answers a region in ~0.1 ms and the compiled CPU pass
(perception.binning) took 1.0-1.3 ms of host CPU a region, so it, not the network, set a grasp
planner's pace; on an H200 this cut makes 3,700-6,200 regions/s against 1,900-2,900 for the
compiled pass on 8 host threads (docs/measurements.md, issue 33). Every point a gel reads is
one element of a flat batch: its region, its run and its place in the sorted cloud come from
``repeat_interleave`` over the runs, and the per-bin minimum is one ``scatter_reduce``; the empty
bins and the sampling gaps are filled there too, so only the float32 maps come back.

The same maps, bit for bit (tests/test_depthmap_tensor.py): the transform is float64 with each
product rounded and summed in the compiled kernel's order (separate tensor operations, no fused
multiply-add), the crop is the same inclusive comparisons, a bin is found by the edge rule itself
(``searchsorted`` on the same float64 edges, where the kernel takes a scaled floor and checks
the edges near one), and a minimum does not depend on the order its values arrive in.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from perception.binning import bin_edges, region_groups
from perception.errors import DepthMapError

# Points handled at once: each costs ~150 bytes of temporaries (its index, region, float64
# coordinates and the gathered transform), so a chunk takes ~1.2 GB of the GPU. Chunks of 2^21
# cost 12-25 % more on an H200 (64-256 gels of a 0.1 mm cloud), in launches and synchronisations.
CHUNK_POINTS = 2**23


def points_on_device(points_m: np.ndarray, device: str | torch.device) -> torch.Tensor:
    """A cloud's points (a VoxelIndex's ``points_m``, float32 or float64, in its sorted order:
    the runs index it) copied once to ``device``, in their own dtype."""
    host = np.ascontiguousarray(points_m)
    if not host.flags.writeable:  # torch shares a NumPy array's memory and may not share a read-only one
        host = host.copy()
    return torch.from_numpy(host).to(device)


def check_device_points(device_points: object, points_m: np.ndarray) -> torch.Tensor:
    """``device_points`` if it can stand for a VoxelIndex's ``points_m`` in the cut: a tensor of
    their shape and dtype, as :func:`points_on_device` copies them; DepthMapError naming the
    argument otherwise. Its values are not compared: that would bring every point back.

    Why the dtype: the cut reads each point in the tensor's own dtype, so a float16 copy moves the
    maps by millimetres and a float32 copy of float64 points is no longer bit for bit the NumPy
    cut; a wider copy would cut the same maps, but only the index's dtype is the index's points."""
    if not isinstance(device_points, torch.Tensor):
        raise DepthMapError(
            f"device_points must be a torch.Tensor (perception.depthmap_tensor.points_on_device), "
            f"got {type(device_points).__name__}"
        )
    if tuple(device_points.shape) != points_m.shape:
        raise DepthMapError(f"device_points {tuple(device_points.shape)} are not the index's {points_m.shape}")
    expected = torch.from_numpy(np.empty(0, points_m.dtype)).dtype
    if device_points.dtype != expected:
        raise DepthMapError(
            f"device_points are {device_points.dtype}, not the index's points' {expected}: "
            "copy them with perception.depthmap_tensor.points_on_device"
        )
    return device_points


def depth_maps_on_device(
    points: torch.Tensor,
    starts: np.ndarray,
    ends: np.ndarray,
    runs: np.ndarray,
    model_to_gel: np.ndarray,
    bounds: tuple[float, float, float, float],
    shape: tuple[int, int],
    fill_min_neighbours: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The depth-maps of perception.depthmap's cut, all on ``points``' device: for region k, the
    points of runs runs[k]..runs[k+1] of (starts, ends) through model_to_gel[k] ((regions, 4, 4)
    float64, model to gel), kept inside ``bounds`` = (half_x, half_z, y_near, y_far) (inclusive,
    metres), their minimum gel y per bin of ``shape`` = (rows, cols), empty bins y_far and
    sampling gaps filled (``fill_min_neighbours`` 1..8; 0: none) as
    perception.binning.fill_sampling_gaps fills them. Returns (depth-maps (regions, rows, cols)
    float32 m, occupied bool, points kept per region int64)."""
    min_y, counts, _ = _min_y_per_region(points, starts, ends, runs, model_to_gel, bounds, shape, keep_points=False)
    occupied = torch.isfinite(min_y)
    depth_maps = torch.where(occupied, min_y, bounds[3]).to(torch.float32)
    if fill_min_neighbours:
        depth_maps = _filled(depth_maps, occupied, fill_min_neighbours)
    return depth_maps.cpu().numpy(), occupied.cpu().numpy(), counts.cpu().numpy()


def front_points_on_device(
    points: torch.Tensor,
    starts: np.ndarray,
    ends: np.ndarray,
    runs: np.ndarray,
    model_to_gel: np.ndarray,
    bounds: tuple[float, float, float, float],
    shape: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """perception.binning.cut_kernel with places, on ``points``' device (arguments as
    :func:`depth_maps_on_device`'s): (min_y, at_x, at_z: (regions, rows * cols) float64, the gel
    y, x, z of each bin's front-most point (the least y, ties by the least x, then z), +inf y and
    0 x, z where empty; points kept per region int64), for perception.surface.surface_maps."""
    regions = model_to_gel.shape[0]
    min_y, counts, kept = _min_y_per_region(points, starts, ends, runs, model_to_gel, bounds, shape, keep_points=True)
    min_y = min_y.reshape(-1)
    at_x, at_z = torch.zeros_like(min_y), torch.zeros_like(min_y)
    if kept:
        bins, x, y, z = (torch.cat(parts) for parts in zip(*kept))
        # Ties are broken by minima too, so the point kept does not depend on the points' order.
        front = y == min_y[bins]
        least_x = torch.full_like(min_y, torch.inf).scatter_reduce_(0, bins[front], x[front], reduce="amin")
        front &= x == least_x[bins]
        least_z = torch.full_like(min_y, torch.inf).scatter_reduce_(0, bins[front], z[front], reduce="amin")
        occupied = torch.isfinite(min_y)
        at_x, at_z = torch.where(occupied, least_x, 0.0), torch.where(occupied, least_z, 0.0)
    return (
        min_y.view(regions, -1).cpu().numpy(),
        at_x.view(regions, -1).cpu().numpy(),
        at_z.view(regions, -1).cpu().numpy(),
        counts.cpu().numpy(),
    )


def _filled(depth_maps: torch.Tensor, occupied: torch.Tensor, min_neighbours: int) -> torch.Tensor:
    """perception.binning.fill_sampling_gaps on (regions, rows, cols) tensors: an empty bin with
    at least ``min_neighbours`` of its 8 neighbours occupied takes their minimum. Counts and
    minima are exact in any order, so the maps are the NumPy function's."""
    rows, cols = depth_maps.shape[-2:]
    flags = F.pad(occupied.to(torch.uint8), (1, 1, 1, 1))
    surface = F.pad(torch.where(occupied, depth_maps, torch.inf), (1, 1, 1, 1), value=torch.inf)
    neighbours = torch.zeros_like(flags[:, 1:-1, 1:-1])
    nearest = torch.full_like(depth_maps, torch.inf)
    for dr in range(3):
        for dc in range(3):
            if (dr, dc) != (1, 1):
                neighbours += flags[:, dr : dr + rows, dc : dc + cols]
                nearest = torch.minimum(nearest, surface[:, dr : dr + rows, dc : dc + cols])
    return torch.where(~occupied & (neighbours >= min_neighbours), nearest, depth_maps)


def _min_y_per_region(
    points: torch.Tensor,
    starts: np.ndarray,
    ends: np.ndarray,
    runs: np.ndarray,
    model_to_gel: np.ndarray,
    bounds: tuple[float, float, float, float],
    shape: tuple[int, int],
    keep_points: bool,
) -> tuple[torch.Tensor, torch.Tensor, list[tuple[torch.Tensor, ...]]]:
    """perception.binning.cut_kernel on ``points``' device: (min_y (regions, rows, cols)
    float64, +inf where empty; points kept per region, int64), as the kernel's; with ``keep_points``,
    each chunk's kept points (flat bin, x, y, z), else none."""
    rows, cols = shape
    regions = model_to_gel.shape[0]
    device = points.device
    half_x, half_z, y_near, y_far = bounds
    lengths = np.asarray(ends, np.int64) - np.asarray(starts, np.int64)
    run_region = torch.from_numpy(np.repeat(np.arange(regions, dtype=np.int64), np.diff(runs))).to(device)
    run_start = torch.from_numpy(np.asarray(starts, np.int64)).to(device)
    run_length = torch.from_numpy(lengths).to(device)
    transforms = torch.from_numpy(np.ascontiguousarray(model_to_gel[:, :3, :], np.float64).reshape(regions, 12))
    transforms = transforms.to(device)
    x_edges = torch.from_numpy(bin_edges(half_x, cols)).to(device)
    z_edges = torch.from_numpy(bin_edges(half_z, rows)).to(device)
    min_y = torch.full((regions * rows * cols,), torch.inf, dtype=torch.float64, device=device)
    counts = torch.zeros(regions, dtype=torch.int64, device=device)
    kept: list[tuple[torch.Tensor, ...]] = []
    chunks = max(1, -(-int(lengths.sum()) // CHUNK_POINTS))
    for first, stop in region_groups(lengths, np.arange(len(lengths) + 1), chunks):  # each run a "region"
        total = int(lengths[first:stop].sum())
        if total == 0:
            continue
        chunk_lengths = run_length[first:stop]
        run = torch.repeat_interleave(torch.arange(first, stop, device=device), chunk_lengths, output_size=total)
        offsets = torch.cumsum(chunk_lengths, 0) - chunk_lengths  # first point of each run in the chunk
        index = run_start[run] + torch.arange(total, device=device) - offsets[run - first]
        region = run_region[run]
        px, py, pz = points[index].to(torch.float64).unbind(1)
        t = transforms[region]
        # The kernel's order: ((a * px + b * py) + c * pz) + d, each product rounded on its own.
        x = t[:, 0] * px + t[:, 1] * py + t[:, 2] * pz + t[:, 3]
        y = t[:, 4] * px + t[:, 5] * py + t[:, 6] * pz + t[:, 7]
        z = t[:, 8] * px + t[:, 9] * py + t[:, 10] * pz + t[:, 11]
        keep = (y >= y_near) & (y <= y_far) & (x.abs() <= half_x) & (z.abs() <= half_z)
        x, y, z, region = x[keep], y[keep], z[keep], region[keep]
        # Bin i holds [edge_i, edge_i+1); the far edge belongs to the last bin.
        col = (torch.searchsorted(x_edges, x, right=True) - 1).clamp_(0, cols - 1)
        row = (torch.searchsorted(z_edges, z, right=True) - 1).clamp_(0, rows - 1)
        flat = region * (rows * cols) + row * cols + col
        min_y.scatter_reduce_(0, flat, y, reduce="amin")
        counts += torch.bincount(region, minlength=regions)
        if keep_points:
            kept.append((flat, x, y, z))
    return min_y.view(regions, rows, cols), counts, kept
