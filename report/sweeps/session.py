"""The sweeps on the report's collected session: how the patch extractor makes depth-maps from
registered models (resolution, point density), scored on the session's test split."""

from __future__ import annotations

import statistics
import time

import numpy as np

from dataset.reader import DatasetReader
from dataset.redepth import depth_map_again, depth_map_params, model_cloud
from models.checkpoint import load_generator
from models.evaluate import PAPER_DENSITY_SSIM
from models.serving import predict
from perception.density import downsample_to_density
from perception.pointcloud import VoxelIndex
from report.specs import Point, point
from report.sweeps.common import epoch_s, median_ms, no_contact_estimate, resize, session_scores
from report.workspace import REFERENCE_SIZE, Workspace


def resolution(ws: Workspace) -> list[Point]:
    """The session's depth-maps made again over 50, 100, 200 bins (tactile images resized to
    match) and a model trained on each -> SSIM of its estimates resized to 100 x 100 against
    the collected 100 x 100 truth, training CPU s/epoch, inference ms per region."""
    test = ws.session_test
    points = []
    for size in ws.plan.resolutions:
        model = ws.session_model(size)
        generator, depth_range = load_generator(model / "checkpoint.pt")
        reader = DatasetReader(ws.session_at(size))
        depth = np.stack([reader.load(r.sample_id).depth_map_m for r in test.records])
        estimate = predict(generator, depth, depth_range)
        inference_ms = median_ms(lambda: predict(generator, depth, depth_range), 3) / len(depth)
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
    params, scene = depth_map_params(DatasetReader(ws.session))
    geometry = scene.gripper_geometry()
    generator, depth_range = load_generator(ws.session_model() / "checkpoint.pt")
    no_contact = no_contact_estimate(generator, depth_range, REFERENCE_SIZE)
    full = {name: model_cloud(scene, name) for name in sorted({r.object_name for r in test.records})}
    points = []
    for value in (None, *ws.plan.densities):
        clouds, thinning = {}, []
        for name, cloud in full.items():
            started = time.perf_counter()
            clouds[name] = VoxelIndex(cloud if value is None else downsample_to_density(cloud, value))
            thinning.append((time.perf_counter() - started) * 1e3)
        maps, walls = [], []
        for record in test.records:
            started = time.perf_counter()
            maps.append(depth_map_again(clouds[record.object_name], np.array(record.model_to_gel), geometry, params))
            walls.append((time.perf_counter() - started) * 1e3)
        scores = session_scores(test, predict(generator, np.stack(maps), depth_range), no_contact)
        points.append(
            point(
                "density",
                "unfiltered" if value is None else f"{value:g} pts/cm³",
                statistics.median(walls),
                scores.pop("contact_ssim"),
                points_median=int(np.median([len(c.points_m) for c in clouds.values()])),
                thinning_ms=round(statistics.median(thinning), 3),
                paper_ssim=None if value is None else PAPER_DENSITY_SSIM.get(int(value)),
                **scores,
            )
        )
    return points
