"""From dataset samples and depth-maps to network tensors, and back."""

from __future__ import annotations

import os
from collections.abc import Sequence

import numba
import numpy as np
import torch

from dataset.reader import DatasetReader
from dataset.records import SampleRecord
from dataset.splits import leave_one_object_out, split_records
from models.networks import GeneratorConfig, ModelConfigError
from models.prior import PhysicsPrior, PriorSpec
from perception.normalisation import normalise_depth_map
from sim.gelsight import MAX_RENDERED_PIXELS


def depth_input(depth_maps_m: np.ndarray, depth_range_m: tuple[float, float], in_channels: int) -> torch.Tensor:
    """N x H x W depth-maps in metres (NaN/+inf = empty bin) -> N x C x H x W float32 network
    input: channel 0 the normalised depth in [-1, 1]; channel 1 (when ``in_channels`` is 2)
    the validity mask, +1 where the bin holds surface nearer than y_far and -1 where it is
    empty (perception.depthmap stores y_far there, other sources NaN or +inf)."""
    maps = np.asarray(depth_maps_m)
    if maps.ndim != 3 or maps.shape[0] == 0 or not np.issubdtype(maps.dtype, np.floating):
        raise ModelConfigError(
            f"depth-maps must be a non-empty N x H x W float array in metres, got {maps.shape} {maps.dtype}"
        )
    if np.any(np.isneginf(maps)):
        raise ModelConfigError("depth-maps contain -inf (empty bins are NaN or +inf)")
    channels = [normalise_depth_map(maps, depth_range_m)]
    if in_channels == 2:
        with np.errstate(invalid="ignore"):  # NaN compares False: an empty bin
            occupied = maps < depth_range_m[1]
        channels.append(np.where(occupied, 1.0, -1.0).astype(np.float32))
    elif in_channels != 1:
        raise ModelConfigError(f"in_channels must be 1 or 2, got {in_channels}")
    return torch.from_numpy(np.stack(channels, axis=1))


def network_input(
    depth_maps_m: np.ndarray,
    depth_range_m: tuple[float, float],
    config: GeneratorConfig,
    prior: PhysicsPrior | None,
    pose_sigma_mm: float | np.ndarray | None = None,
) -> torch.Tensor:
    """What a generator of ``config`` takes for N x H x W depth-maps (m): :func:`depth_input`,
    then the physics prior's image of each map (models.prior) when the generator has one,
    expected over the maps' in-plane pose error ``pose_sigma_mm`` (mm: one for all maps, or N,
    one a map; None: the prior's default). On the prior's device: a GPU's never leaves it."""
    x = depth_input(depth_maps_m, depth_range_m, config.in_channels)
    if not config.prior:
        return x
    if prior is None:
        raise ModelConfigError(
            "this generator corrects a physics prior, but none was given (a checkpoint "
            "trained with one stores its scene and crop: load it with load_generator)"
        )
    maps = np.asarray(depth_maps_m)
    if isinstance(pose_sigma_mm, np.ndarray):
        if pose_sigma_mm.shape != (len(maps),):
            raise ModelConfigError(
                f"pose_sigma_mm must be one value or one per depth-map ({len(maps)}), got shape {pose_sigma_mm.shape}"
            )
        channels = torch.cat([prior.channels(m[None], float(s)) for m, s in zip(maps, pose_sigma_mm)])
    else:
        # A dataset's maps in calls the renderer takes (MAX_RENDERED_PIXELS): 1,680 maps at
        # 200 x 200 are one pixel too many for one.
        h, w = prior.renderer.config.shape
        per_call = max(1, MAX_RENDERED_PIXELS // (h * w))
        channels = torch.cat(
            [prior.channels(maps[i : i + per_call], pose_sigma_mm) for i in range(0, max(len(maps), 1), per_call)]
        )
    return torch.cat([x.to(channels.device), channels], dim=1)


def moved_in_gel_plane(
    depth_maps_m: np.ndarray, offsets_mm: np.ndarray, crop_m: tuple[float, float, float], y_far_m: float
) -> np.ndarray:
    """N x H x W depth-maps as a registration ``offsets_mm`` off in the gel plane (N x 2: gel x
    along columns, gel z along rows) would have cut them: each map's surface moved by its offset,
    to the nearest bin of the crop (x, y, z extents in m); the bins it leaves hold ``y_far_m``
    (no surface), and what moves past the crop's edge is lost, as it is to the cutter."""
    maps = np.asarray(depth_maps_m)
    rows, cols = maps.shape[1:]
    bins = np.rint(np.asarray(offsets_mm) / (1e3 * np.array([crop_m[0] / cols, crop_m[2] / rows]))).astype(int)
    moved = np.full_like(maps, y_far_m)
    for source, target, (dc, dr) in zip(maps, moved, bins):
        if abs(dr) < rows and abs(dc) < cols:
            target[max(dr, 0) : rows + min(dr, 0), max(dc, 0) : cols + min(dc, 0)] = source[
                max(-dr, 0) : rows - max(dr, 0), max(-dc, 0) : cols - max(dc, 0)
            ]
    return moved


def image_target(images_rgb: np.ndarray) -> torch.Tensor:
    """N x H x W x 3 uint8 RGB -> N x 3 x H x W float32 in [-1, 1] (the tanh range)."""
    images = np.asarray(images_rgb)
    if images.dtype != np.uint8 or images.ndim != 4 or images.shape[-1] != 3:
        raise ModelConfigError(f"tactile images must be N x H x W x 3 uint8, got {images.shape} {images.dtype}")
    return torch.from_numpy(images).permute(0, 3, 1, 2).float() / 127.5 - 1.0


def to_uint8_rgb(images: torch.Tensor) -> np.ndarray:
    """Network output N x 3 x H x W in [-1, 1] -> N x H x W x 3 uint8 (rounded, clipped), C-contiguous:
    round((x + 1) * 127.5) in float32, halves to even, clipped to 0..255 (:func:`_image_levels`;
    a GPU's images levelled there in PyTorch's own arithmetic, so that a quarter of the bytes
    come back: 2.9-7.5 ms of a 64-region request on a lent H200 as float32 and a host pass)."""
    if images.device.type != "cpu":
        levels_on_device = ((images.detach().float() + 1.0) * 127.5).round().clamp(0.0, 255.0).to(torch.uint8)
        return levels_on_device.permute(0, 2, 3, 1).contiguous().cpu().numpy()
    units = np.ascontiguousarray(images.detach().float().numpy())
    levels = np.empty((units.shape[0], *units.shape[2:], units.shape[1]), np.uint8)
    _image_levels(units, levels)
    return levels


@numba.njit(cache=True, nogil=True)
def _image_levels(units: np.ndarray, levels: np.ndarray) -> None:
    """levels[i, r, c, k] = units[i, k, r, c] as :func:`to_uint8_rgb` rounds it. Why compiled: in
    PyTorch the shift, scale, round, clip, cast and the channels moved last are six passes over a
    served reply's images, 0.042 ms a region where the lanes serve ~1.4; here one pass, a row of a
    channel at a time in vector instructions, 0.007 ms."""
    count, channels, rows, cols = units.shape
    row = np.empty(cols, np.uint8)
    for i in range(count):
        for k in range(channels):
            for r in range(rows):
                for c in range(cols):
                    level = np.rint((units[i, k, r, c] + np.float32(1.0)) * np.float32(127.5))
                    row[c] = np.uint8(min(max(level, np.float32(0.0)), np.float32(255.0)))
                for c in range(cols):
                    levels[i, r, c, k] = row[c]


def select_records(reader: DatasetReader, split: str, hold_out_object: str = "") -> list[SampleRecord]:
    """Records of one split: the dataset's 70/15/15 split, or with ``hold_out_object`` the
    leave-one-object-out split (its "test" is every sample of that object)."""
    seed = reader.info.split_seed
    splits = (
        leave_one_object_out(reader.records, hold_out_object, seed)
        if hold_out_object
        else split_records(reader.records, seed)
    )
    if split not in splits:
        raise ModelConfigError(f"unknown split {split!r}; known: {sorted(splits)}")
    return splits[split]


def reader_for_model(root: str | os.PathLike[str], depth_range_m: tuple[float, float]) -> DatasetReader:
    """The dataset at ``root``, refused unless it normalises depth as the model was trained."""
    reader = DatasetReader(root)
    if tuple(reader.info.depth_range_m) != tuple(depth_range_m):
        raise ModelConfigError(
            f"{root} normalises depth with {reader.info.depth_range_m}, the model was trained with {depth_range_m}"
        )
    return reader


def load_pairs(
    root: str | os.PathLike[str] | DatasetReader,
    records: Sequence[SampleRecord] | None,
    config: GeneratorConfig,
    prior: PhysicsPrior | None = None,
    pose_sigma_mm: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Network input (:func:`network_input`) and target (N x C x H x W, N x 3 x H x W) for
    ``records`` (all if None), checksums verified."""
    reader = root if isinstance(root, DatasetReader) else DatasetReader(root)
    maps, images = load_samples(reader, records)
    return network_input(maps, reader.info.depth_range_m, config, prior, pose_sigma_mm), image_target(images)


def load_samples(reader: DatasetReader, records: Sequence[SampleRecord] | None) -> tuple[np.ndarray, np.ndarray]:
    """Depth-maps (m) and tactile images of ``records`` (all if None), checksums verified."""
    chosen = reader.records if records is None else list(records)
    if not chosen:
        raise ModelConfigError(f"no samples selected from {reader.root}")
    samples = [reader.load(r) for r in chosen]
    return np.stack([s.depth_map_m for s in samples]), np.stack([s.tactile_rgb for s in samples])


def session_prior(reader: DatasetReader, config: GeneratorConfig, pose_sigma_mm: float = 0.0) -> PhysicsPrior | None:
    """The physics prior for a generator of ``config`` trained on ``reader``'s dataset: its
    scene's GelSight, its depth-maps' crop and their pose error (None when the config has no prior)."""
    if not config.prior:
        return None
    if reader.info.depth_crop_m is None or not reader.info.scene:
        raise ModelConfigError(f"{reader.root} does not record its scene and depth crop, which a physics prior needs")
    spec = PriorSpec(
        reader.info.scene, reader.info.depth_crop_m, pose_sigma_mm, config.prior_drawn_at, config.prior_drawn_rows
    )
    return PhysicsPrior(spec, config.image_size)
