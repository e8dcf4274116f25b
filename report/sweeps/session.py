"""The sweeps on the report's collected session: how the patch extractor makes depth-maps from
registered models (resolution, point density, the bin rule) and what pose error the served
model is told of, scored on the session's test split."""

from __future__ import annotations

import dataclasses
import functools
import statistics
import time
from typing import NamedTuple

import numpy as np

from dataset.reader import DatasetReader
from dataset.redepth import depth_map_again, depth_map_params, model_cloud, model_index
from models.checkpoint import load_generator
from models.evaluate import PAPER_DENSITY_SSIM
from models.serving import predict
from perception.density import downsample_to_density
from perception.depthmap import DepthMapParams
from perception.pointcloud import VoxelIndex
from report.specs import Point, point
from report.sweeps.common import (
    dissimilarity_ratio,
    epoch_s,
    median_cpu_ms,
    no_contact_estimate,
    renderer_ratio,
    resize,
    session_scores,
)
from report.workspace import REFERENCE_SIZE, SessionTest, Workspace
from workcell.kinematics import GripperGeometry
from workcell.scene import Scene


def resolution(ws: Workspace) -> list[Point]:
    """The session's depth-maps made again over 50, 100, 200 bins (tactile images resized to
    match) and a model trained on each -> SSIM of its estimates resized to 100 x 100 against
    the collected 100 x 100 truth, training CPU s/epoch, inference ms per region."""
    test = ws.session_test
    points = []
    for size in ws.plan.resolutions:
        model = ws.session_model(size)
        generator, depth_range = load_generator(model / "checkpoint.pt")
        depth = test.depth_maps(ws.session_at(size))
        estimate = predict(generator, depth, depth_range)
        inference_ms = median_cpu_ms(lambda: predict(generator, depth, depth_range), 3) / len(depth)
        scores = session_scores(
            test, resize(estimate, REFERENCE_SIZE), no_contact_estimate(generator, depth_range, size)
        )
        points.append(
            point(
                "resolution",
                f"{size} x {size}",
                epoch_s(model),
                scores.pop("contact_ssim"),
                inference_ms_per_region=round(inference_ms, 3),
                **scores,
            )
        )
    return points


def density(ws: Workspace) -> list[Point]:
    """The session's test grasps with each object's model cloud (the patch extractor's)
    voxel-thinned to each density and their depth-maps made again from the recorded model
    poses (dataset.redepth), estimated by the model trained on the session -> SSIM; time =
    making one depth-map (the pipeline thins a model cloud once and cuts many depth-maps from
    it, so thinning and indexing are reported beside, not added)."""
    test = ws.session_test
    cutters = _cutters(ws)
    generator, depth_range = load_generator(ws.session_model() / "checkpoint.pt")
    no_contact = no_contact_estimate(generator, depth_range, REFERENCE_SIZE)
    full = {key: model_cloud(scene, key[1]) for key, scene in _objects(test, cutters).items()}
    points = []
    for value in (None, *ws.plan.densities):
        clouds, thinning = {}, []
        for key, cloud in full.items():
            started = time.process_time()
            clouds[key] = VoxelIndex(cloud if value is None else downsample_to_density(cloud, value))
            thinning.append((time.process_time() - started) * 1e3)
        maps, cut_ms = _cut_again(test, clouds, cutters)
        scores = session_scores(test, predict(generator, maps, depth_range), no_contact)
        points.append(
            point(
                "density",
                "unfiltered" if value is None else f"{value:g} pts/cm³",
                cut_ms,
                scores.pop("contact_ssim"),
                points_median=int(np.median([len(c.points_m) for c in clouds.values()])),
                thinning_ms=round(statistics.median(thinning), 3),
                paper_ssim=None if value is None else PAPER_DENSITY_SSIM.get(int(value)),
                **scores,
            )
        )
    return points


def depth_map(ws: Workspace) -> list[Point]:
    """The session's depth-maps cut again by each rule of ``plan.depth_map_methods``
    (perception.surface) and the model trained as the default is on each (session and contact
    library by that rule) -> contact SSIM of its estimates from the test split's maps; time =
    cutting one depth-map by that rule from the recorded model pose (ms, as the density sweep
    times it). Beside it the maps through the GelSight renderer and the served estimate's
    dissimilarity ratio, each scored as ``dtx evaluate`` scores a model."""
    test = ws.session_test
    cutters = _cutters(ws)
    clouds = {key: model_index(scene, key[1]) for key, scene in _objects(test, cutters).items()}
    # The sessions of one model share its GelSight and depth crop (models.sessions.check_one_prior).
    depth_crop_m = DatasetReader(ws.session).info.depth_crop_m
    points = []
    for method in ws.plan.depth_map_methods:
        model = ws.session_model(REFERENCE_SIZE, method)
        generator, depth_range = load_generator(model / "checkpoint.pt")
        by_rule = [c._replace(params=dataclasses.replace(c.params, method=method)) for c in cutters]
        maps, cut_ms = _cut_again(test, clouds, by_rule)
        estimate = predict(generator, maps, depth_range)
        scores = session_scores(test, estimate, no_contact_estimate(generator, depth_range, REFERENCE_SIZE))
        points.append(
            point(
                "depth_map",
                method,
                cut_ms,
                scores.pop("contact_ssim"),
                training_s_per_epoch=round(epoch_s(model), 2),
                dissimilarity_ratio=dissimilarity_ratio(test, estimate),
                **renderer_ratio(test, cutters[0].scene, depth_crop_m, maps),
                **scores,
            )
        )
    return points


def pose_sigma(ws: Workspace) -> list[Point]:
    """The session model served with each in-plane pose error ``pose_sigma_mm`` of
    ``plan.pose_sigmas_mm`` and its own default (its training session's, ``model_default``)
    that its physics prior is blurred by (models.serving.predict) -> contact SSIM of its
    estimates from the test split's recorded maps; time = ms per region of the served estimate:
    what a planner should pass as pose_sigma_mm."""
    test = ws.session_test
    generator, depth_range = load_generator(ws.session_model() / "checkpoint.pt")
    if generator.prior is None:
        raise RuntimeError("the session model corrects no physics prior: pose_sigma_mm changes nothing it serves")
    default = generator.prior.spec.pose_sigma_mm
    depth = test.depth_maps(ws.sessions)
    points = []
    for sigma in sorted({*ws.plan.pose_sigmas_mm, default}):
        estimate = predict(generator, depth, depth_range, pose_sigma_mm=sigma)
        served_ms = median_cpu_ms(functools.partial(predict, generator, depth, depth_range, pose_sigma_mm=sigma), 3)
        no_contact = no_contact_estimate(generator, depth_range, REFERENCE_SIZE, sigma)
        scores = session_scores(test, estimate, no_contact)
        points.append(
            point(
                "pose_sigma",
                f"{sigma:g} mm",
                served_ms / len(depth),
                scores.pop("contact_ssim"),
                model_default=sigma == default,
                dissimilarity_ratio=dissimilarity_ratio(test, estimate),
                **scores,
            )
        )
    return points


class Cutter(NamedTuple):
    """How a session's patch extractor cut its depth-maps: its scene (whose models the objects
    are) and that scene's file, gripper and depth-map settings."""

    scene_file: str
    scene: Scene
    geometry: GripperGeometry
    params: DepthMapParams


def _cutters(ws: Workspace) -> list[Cutter]:
    """Each session's :class:`Cutter`, in the workspace's order."""
    cutters = []
    for session in ws.sessions:
        reader = DatasetReader(session)
        params, scene = depth_map_params(reader)
        cutters.append(Cutter(reader.info.scene, scene, scene.gripper_geometry(), params))
    return cutters


def _objects(test: SessionTest, cutters: list[Cutter]) -> dict[tuple[str, str], Scene]:
    """The test split's objects, each once, by (its session's scene file, object name): the scene
    that holds its model."""
    objects = {}
    for record, session in zip(test.records, test.session_of):
        cutter = cutters[int(session)]
        objects[(cutter.scene_file, record.object_name)] = cutter.scene
    return dict(sorted(objects.items()))


def _cut_again(
    test: SessionTest, clouds: dict[tuple[str, str], VoxelIndex], cutters: list[Cutter]
) -> tuple[np.ndarray, float]:
    """The test split's depth-maps (N x H x W, m) cut again from ``clouds`` ((scene file, object
    name) -> indexed model cloud: :func:`_objects`) at the recorded model poses, each by its
    session's cutter, and the median ms of one cut (the cloud indexed beforehand, as the patch
    extractor indexes it once per object)."""
    maps, walls = [], []
    for record, session in zip(test.records, test.session_of):
        cutter = cutters[int(session)]
        cloud = clouds[(cutter.scene_file, record.object_name)]
        started = time.process_time()
        maps.append(depth_map_again(cloud, np.array(record.model_to_gel), cutter.geometry, cutter.params))
        walls.append((time.process_time() - started) * 1e3)
    return np.stack(maps), statistics.median(walls)
