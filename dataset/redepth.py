"""Depth-maps made again from a collected dataset, e.g. at the paper's point densities or at
another number of bins.

A collected sample records where the object's model sat in the gel frame when its depth-map
was made (``model_to_gel``), and the dataset records the crop (``depth_crop_m``) and the scene
whose meshes the models come from. That is enough to bin the model again: from a cloud thinned
by a voxel-grid filter to 1-80 points/cm³ (paper Table II), or at full density, which gives
back the collected maps bit for bit. Tactile images are copied unchanged (resized with the
depth-map when the bins change, since the network maps one bin to one pixel) and the sample
ids are kept, so the splits are the same and one checkpoint evaluates every variant of its size.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import multiprocessing
import os
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from dataset.images import resize_rgb
from dataset.reader import DatasetReader
from dataset.records import FINGERS, DatasetError, DatasetInfo, Sample, SampleRecord
from dataset.writer import DatasetWriter
from msgs.progress import track
from perception.density import downsample_to_density
from perception.depthmap import (
    MODEL_CLOUD_SEED,
    MODEL_POINT_SPACING_M,
    DepthMapParams,
    contact_depth_map,
    crop_bounds,
    crop_reach_m,
)
from perception.errors import OutOfReachError
from perception.gripper_centring import centre_between_gels
from perception.pointcloud import VoxelIndex, check_transform, transform_points
from perception.registration import sample_model_cloud
from perception.surface import DEPTH_MAP_METHODS
from workcell.kinematics import GripperGeometry
from workcell.scene import Scene, SceneError, load_scene

PosesBySample = dict[str, tuple[np.ndarray, np.ndarray]]  # sample id -> (model_to_gel, model_to_world)


def depth_map_params(reader: DatasetReader) -> tuple[DepthMapParams, Scene]:
    """The depth-map settings the dataset's maps were made with, and its scene."""
    info = reader.info
    if info.depth_crop_m is None:
        raise DatasetError(
            f"{reader.root} records no depth-map crop (dataset.json depth_crop_m): it was not "
            "made from registered models and its depth-maps cannot be made again"
        )
    scene = load_scene(info.scene)
    geometry = scene.gripper_geometry()
    sensed_x, sensed_z = geometry.sensed_extent_m
    margin_x, margin_z = 0.5 * (info.depth_crop_m[0] - sensed_x), 0.5 * (info.depth_crop_m[2] - sensed_z)
    if abs(margin_x - margin_z) > 1e-9:
        raise DatasetError(
            f"{reader.root}: crop {info.depth_crop_m} m does not fit the scene's sensed area "
            f"({sensed_x}, {sensed_z}) m with one margin"
        )
    shape = reader.load(reader.records[0], verify=False).depth_map_m.shape
    params = DepthMapParams(shape=shape, margin_m=margin_x, y_range_m=info.depth_range_m, method=info.depth_map_method)
    return params, scene


def model_cloud(scene: Scene, object_name: str, points_per_cm3: float | None = None) -> np.ndarray:
    """The patch extractor's model cloud of one object (N x 3, model frame, m, read-only):
    MODEL_POINT_SPACING_M apart, seed MODEL_CLOUD_SEED, voxel-thinned to ``points_per_cm3``
    unless None. Raises SceneError for an object the scene does not have."""
    return _model_cloud(scene.mesh(object_name), points_per_cm3)


def model_index(scene: Scene, object_name: str, points_per_cm3: float | None = None) -> VoxelIndex:
    """:func:`model_cloud` indexed as the patch extractor indexes it."""
    return _model_index(scene.mesh(object_name), points_per_cm3)


# Sampling a mesh and indexing the cloud take seconds: once per process, for the centring, the
# full-density maps and every density thinned from the same cloud.
@functools.lru_cache(maxsize=32)
def _model_cloud(mesh_path: str, points_per_cm3: float | None) -> np.ndarray:
    if points_per_cm3 is None:
        cloud = sample_model_cloud(mesh_path, MODEL_POINT_SPACING_M, seed=MODEL_CLOUD_SEED).points_m
    else:
        cloud = downsample_to_density(_model_cloud(mesh_path, None), points_per_cm3)
    cloud.setflags(write=False)
    return cloud


@functools.lru_cache(maxsize=32)
def _model_index(mesh_path: str, points_per_cm3: float | None) -> VoxelIndex:
    return VoxelIndex(_model_cloud(mesh_path, points_per_cm3))


def depth_map_again(
    model: VoxelIndex, model_to_gel: np.ndarray, geometry: GripperGeometry, params: DepthMapParams
) -> np.ndarray:
    """The depth-map (m, float32) of a model cloud (indexed as the patch extractor indexes it)
    posed in the gel frame by ``model_to_gel``, with a dataset's settings
    (:func:`depth_map_params`), from the points within reach of the gel as the patch extractor
    takes them; y_far everywhere when nothing of the cloud falls in the crop ("nothing within
    reach"). ``model_to_gel`` must be rigid (PointCloudError) and ``params`` as
    perception.depthmap.crop_bounds takes them, its default depth range too (DepthMapError)."""
    y_far = crop_bounds(geometry, params)[3]
    gel_centre_in_model = np.linalg.inv(check_transform(model_to_gel, "model_to_gel"))[:3, 3]
    near = model.within(gel_centre_in_model, crop_reach_m(geometry, params))
    try:
        return contact_depth_map(near, model_to_gel, np.eye(4), geometry, params).depth_map_m
    except OutOfReachError:
        return np.full(params.shape, y_far, np.float32)


def redepth_dataset(
    source: str | os.PathLike[str],
    out: str | os.PathLike[str],
    points_per_cm3: float | None = None,
    bins: int | None = None,
    progress: bool = True,
    registered: dict[str, np.ndarray] | None = None,
    method: str | None = None,
) -> DatasetWriter:
    """:func:`redepth_datasets` with one target: ``out`` at ``points_per_cm3``."""
    return redepth_datasets(source, {points_per_cm3: out}, bins, progress, registered, method=method)[points_per_cm3]


def redepth_datasets(
    source: str | os.PathLike[str],
    targets: Mapping[float | None, str | os.PathLike[str]],
    bins: int | None = None,
    progress: bool = True,
    registered: dict[str, np.ndarray] | None = None,
    jobs: int = 1,
    method: str | None = None,
) -> dict[float | None, DatasetWriter]:
    """Write each target directory: ``source`` with every depth-map made again from the model
    cloud (the patch extractor's: MODEL_POINT_SPACING_M apart, seed MODEL_CLOUD_SEED),
    voxel-thinned to the target's points/cm³ unless None, over ``bins`` x ``bins`` bins of the
    same crop unless None (the source's bins), each bin holding what ``method`` says
    (perception.surface; None: the source's). One pass over ``source``: each sample is read
    once for every target. A map whose thinned cloud leaves the crop empty holds y_far
    everywhere ("nothing within reach"), as an empty bin does. A target that already holds
    samples is resumed.

    ``registered`` (object name -> model_to_world, e.g. registered again with a corrected
    calibration, ``dataset.registered_again.register_again``) moves each model there first,
    centred between its grasp's two gels as the patch extractor centres it; the samples must
    record their gels' poses.

    ``jobs`` > 1 shares the targets out among that many processes, each making one pass."""
    if not (isinstance(jobs, int) and jobs >= 1):
        raise DatasetError(f"jobs must be a whole number >= 1, got {jobs!r}")
    reader = DatasetReader(source)
    params, scene = depth_map_params(reader)
    params, info = _with_settings(params, reader.info, bins, method)
    missing = [r.sample_id for r in reader.records if r.model_to_gel is None]
    if missing:
        raise DatasetError(f"{reader.root}: {len(missing)} samples (e.g. {missing[0]}) record no model_to_gel")
    poses = poses_at(reader.records, registered, scene, params) if registered is not None else {}
    if jobs == 1 or len(targets) == 1:
        return _one_pass(reader, scene, params, info, targets, progress, poses)
    workers = min(jobs, len(targets))
    shares = [dict(list(targets.items())[i::workers]) for i in range(workers)]
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        for done in [
            pool.submit(_one_pass_in_process, source, bins, method, share, progress, poses) for share in shares
        ]:
            done.result()
    return {density: DatasetWriter(out, info) for density, out in targets.items()}


def _one_pass(
    reader: DatasetReader,
    scene: Scene,
    params: DepthMapParams,
    info: DatasetInfo,
    targets: Mapping[float | None, str | os.PathLike[str]],
    progress: bool,
    poses: PosesBySample,
) -> dict[float | None, DatasetWriter]:
    """The targets written in one pass over ``reader``'s samples, each model at its pose in
    ``poses`` (a sample without one: as recorded)."""
    geometry = scene.gripper_geometry()
    writers = {density: DatasetWriter(out, info) for density, out in targets.items()}
    densities = ", ".join("full density" if d is None else f"{d:g} points/cm³" for d in writers)
    for record in track(reader.records, f"depth-maps at {densities}", "samples", enabled=progress):
        pending = {d: w for d, w in writers.items() if record.sample_id not in w}  # resumed
        if not pending:
            continue
        sample = reader.load(record)
        model_to_gel, model_to_world = poses.get(record.sample_id, (record.model_to_gel, record.model_to_world))
        fields = _kept_fields(sample, params.shape, model_to_gel, model_to_world)
        for density, writer in pending.items():
            depth_map = _record_map_again(reader, scene, record, density, model_to_gel, geometry, params)
            writer.write(depth_map_m=depth_map, **fields)
    return writers


def _record_map_again(
    reader: DatasetReader,
    scene: Scene,
    record: SampleRecord,
    points_per_cm3: float | None,
    model_to_gel: Any,
    geometry: GripperGeometry,
    params: DepthMapParams,
) -> np.ndarray:
    """:func:`depth_map_again` of ``record``'s object at ``points_per_cm3`` posed by
    ``model_to_gel``; DatasetError naming the sample for an object the scene lacks."""
    try:
        model = model_index(scene, record.object_name, points_per_cm3)
    except SceneError as err:
        raise DatasetError(f"{reader.root}: sample {record.sample_id}: {err}") from err
    return depth_map_again(model, np.array(model_to_gel), geometry, params)


def _one_pass_in_process(
    source: str | os.PathLike[str],
    bins: int | None,
    method: str | None,
    targets: Mapping[float | None, str | os.PathLike[str]],
    progress: bool,
    poses: PosesBySample,
) -> None:
    """:func:`_one_pass` in a process of its own: the poses are the parent's, centred once."""
    reader = DatasetReader(source)
    params, scene = depth_map_params(reader)
    params, info = _with_settings(params, reader.info, bins, method)
    _one_pass(reader, scene, params, info, targets, progress, poses)


def depth_maps_at_density(reader: DatasetReader, records: list[SampleRecord], points_per_cm3: float) -> np.ndarray:
    """The depth-maps (N x H x W, m, float32) of ``records`` of ``reader``'s dataset made again
    from the model cloud voxel-thinned to ``points_per_cm3``, at the poses they record: what
    ``dtx dataset redepth --density`` writes for them, without writing a dataset."""
    params, scene = depth_map_params(reader)
    geometry = scene.gripper_geometry()
    maps = np.empty((len(records), *params.shape), np.float32)
    for i, record in enumerate(records):
        if record.model_to_gel is None:
            raise DatasetError(f"{reader.root}: sample {record.sample_id} records no model_to_gel")
        maps[i] = _record_map_again(reader, scene, record, points_per_cm3, record.model_to_gel, geometry, params)
    return maps


@contextlib.contextmanager
def depth_maps_made_beside(
    root: str | os.PathLike[str], sample_ids: list[str], densities: Sequence[float]
) -> Iterator[dict[float, Future[np.ndarray]]]:
    """:func:`depth_maps_at_density` of the samples ``sample_ids`` of the dataset at ``root``, at
    each of ``densities`` in turn, made in a process of their own while the caller goes on (the
    evaluator scores its full-density estimates meanwhile): density -> its maps, to come. Maps
    not yet made when the block ends are not made."""
    # At the lowest priority: the caller's threads (the network's OpenMP pool) keep their cores,
    # and the maps take what they leave; sharing as equals made both slower than in turn.
    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=os.nice, initargs=(19,))
    try:
        yield {d: pool.submit(_maps_at_density_in_process, str(root), sample_ids, d) for d in densities}
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _maps_at_density_in_process(root: str, sample_ids: list[str], points_per_cm3: float) -> np.ndarray:
    reader = _dataset_in_process(root)
    by_id = {r.sample_id: r for r in reader.records}
    return depth_maps_at_density(reader, [by_id[sample_id] for sample_id in sample_ids], points_per_cm3)


@functools.lru_cache(maxsize=1)
def _dataset_in_process(root: str) -> DatasetReader:
    """The dataset the process's every density is made from, opened once."""
    return DatasetReader(root)


def _kept_fields(sample: Sample, shape: tuple[int, int], model_to_gel: Any, model_to_world: Any) -> dict[str, Any]:
    """A sample's fields as a redepth writes them, all but its depth-map: its tactile images
    resized to ``shape`` (rows, cols) when that differs, its model at the poses given."""
    record = sample.record
    return dict(
        sample_id=record.sample_id,
        object_name=record.object_name,
        grasp_id=record.grasp_id,
        finger=record.finger,
        grasp_pose=record.grasp_pose,
        tactile_rgb=resize_rgb(sample.tactile_rgb, *shape),
        tactile_diff_rgb=resize_rgb(sample.tactile_diff_rgb, *shape),
        registration_fitness=record.registration_fitness,
        stamps_ns=record.stamps_ns,
        model_to_gel=np.array(model_to_gel),
        gel_to_world=None if record.gel_to_world is None else np.array(record.gel_to_world),
        model_to_world=None if model_to_world is None else np.array(model_to_world),
    )


def _with_settings(
    params: DepthMapParams, info: DatasetInfo, bins: int | None, method: str | None
) -> tuple[DepthMapParams, DatasetInfo]:
    """The depth-map settings and dataset facts at ``bins`` x ``bins`` bins and by ``method``
    (None: as they are)."""
    if method is not None:
        if method not in DEPTH_MAP_METHODS:
            raise DatasetError(f"depth-map method must be one of {', '.join(DEPTH_MAP_METHODS)}, got {method!r}")
        params, info = dataclasses.replace(params, method=method), dataclasses.replace(info, depth_map_method=method)
    if bins is None:
        return params, info
    if not (isinstance(bins, int) and 8 <= bins <= 1024):
        raise DatasetError(f"bins must be a whole number from 8 to 1024, got {bins!r}")
    return dataclasses.replace(params, shape=(bins, bins)), dataclasses.replace(
        info, image_height=bins, image_width=bins
    )


def poses_at(
    records: list[SampleRecord], registered: dict[str, np.ndarray], scene: Scene, params: DepthMapParams
) -> PosesBySample:
    """Each sample's (model_to_gel, model_to_world) with its object at ``registered``, centred
    between its grasp's gels as the patch extractor centres it (perception.depthmap)."""
    gels: dict[str, dict[str, np.ndarray]] = {}
    for record in records:
        if record.gel_to_world is None:
            raise DatasetError(f"sample {record.sample_id} records no gel_to_world: its depth-map cannot be cut again")
        if record.object_name not in registered:
            raise DatasetError(f"sample {record.sample_id}: no registered pose given for {record.object_name}")
        gels.setdefault(record.grasp_key, {})[record.finger] = np.array(record.gel_to_world)
    geometry = scene.gripper_geometry()
    reach = crop_reach_m(geometry, params)
    centred: dict[str, np.ndarray] = {}  # by grasp: its two fingers share one centring
    poses = {}
    for record in records:
        pair, model_to_world = gels[record.grasp_key], registered[record.object_name]
        if set(pair) != set(FINGERS):
            raise DatasetError(f"grasp {record.grasp_key} lacks a finger's sample: it cannot be centred again")
        if record.grasp_key not in centred:
            dense = model_index(scene, record.object_name)
            world_to_model = np.linalg.inv(model_to_world)
            near = [dense.within(transform_points(gel[:3, 3][None], world_to_model)[0], reach) for gel in pair.values()]
            centred[record.grasp_key] = centre_between_gels(
                np.concatenate(near),
                model_to_world,
                pair["left"],
                pair["right"],
                geometry,
                scene.gripper.grasp_force_n,
                scene.gripper.foundation_stiffness_n_per_mm3,
            )
        poses[record.sample_id] = (np.linalg.inv(pair[record.finger]) @ centred[record.grasp_key], model_to_world)
    return poses


def density_dirs(root: str | os.PathLike[str], densities: list[float]) -> dict[float, Path]:
    """Where ``dtx dataset redepth`` puts each density of ``root`` by default."""
    return {d: Path(root).with_name(f"{Path(root).name}_density_{d:g}") for d in densities}
