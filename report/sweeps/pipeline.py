"""The accuracy-time report's pipeline rows (report.pipeline): on the report's own session and its
default model (report.workspace; nothing is trained or collected again), what each stage of a
grasp, of a session and of a planner's region costs, and the figure each buys."""

from __future__ import annotations

import json
from typing import Any

import cv2
import numpy as np
import torch

from benchmarks._serve_stages import served_network, stage_costs
from dataset.check import check_dataset
from dataset.reader import DatasetReader
from dataset.redepth import depth_map_params, model_index, poses_at
from dataset.registered_again import placement_report
from dataset.touch_calibration import scene_camera_truth
from models.checkpoint import load_generator
from models.data import network_input, to_uint8_rgb
from models.networks import UNetGenerator
from models.serving import predict_served, prior_images
from models.uncertainty import uncertainty_statistics
from perception.depthmap import contact_depth_maps
from perception.ssim import ssim_rgb
from perception.touch_calibration import TouchCalibrationError, pose_error
from report.pipeline import GRASP, PIPELINE, REGION, SESSION, WHOLE_GRASP, grasp_points
from report.specs import Point, point
from report.sweeps.calibration import _given_extrinsics, _seconds_per_grasp
from report.sweeps.common import dissimilarity_ratio, renderer_ratio
from report.workspace import Workspace, epoch_cpu_s

# Timing repeats of each region stage (the best is kept: the least disturbed on a shared machine).
REPEATS = 3
MAX_BATCH = 16  # regions a forward pass, as the inference node's default


def pipeline(ws: Workspace) -> list[Point]:
    """The grasp's stages from the session's session.json, then the session's calibration and
    training, then a region's serving stages (report.pipeline's rows, in that order)."""
    return [*grasp_stages(ws), *touch_calibration(ws), _training(ws), *_regions(ws)]


def grasp_stages(ws: Workspace) -> list[Point]:
    """The collector's stage medians beside: the registrations' ADD-S (mm) against the scene's
    placements, the renderer ratio of the test split's recorded depth-maps, and the dataset
    check's problem count; then the whole grasp at the session's pace (first to last GelSight
    frame over the grasps between, a pause of a resumed session included)."""
    summary_file = ws.collected / "session.json"
    summary = json.loads(summary_file.read_text()) if summary_file.exists() else None
    reader = DatasetReader(ws.collected)
    registered = {r.object_name: np.array(r.model_to_world) for r in reader.records if r.model_to_world is not None}
    add_s = [row["add_s_mm"] for row in placement_report(ws.collected, registered).values() if "add_s_mm" in row]
    _, scene = depth_map_params(reader)
    recorded = ws.first_test.depth_maps([ws.collected])  # as its patch extractor cut them
    figures = {
        "register": float(np.median(add_s)) if add_s else None,  # None: a scene whose poses are not known
        "depth_maps": renderer_ratio(ws.first_test, scene, reader.info.depth_crop_m, recorded)["renderer_ratio"],
        "write": float(len(check_dataset(ws.collected).problems)),
    }
    # The whole grasp from the dataset's own stamps: a resumed session's session.json times
    # only the grasps of its last run, and counts its pairs but not its grasps.
    grasps = len({r.grasp_key for r in reader.records})
    whole = point(
        PIPELINE,
        WHOLE_GRASP,
        _seconds_per_grasp(reader.records),
        len(reader.records) / grasps,
        per=GRASP,
        unit="s",
        buys="pairs written per grasp",
    )
    return [*grasp_points(summary, figures), whole]


def touch_calibration(ws: Workspace) -> list[Point]:
    """``dtx calibrate touches`` on the whole session: its CPU s, and the worse camera's error
    (mm) against the scene's truth after it, beside the error before (the given extrinsics)."""
    extra = {"per": SESSION, "unit": "CPU s", "buys": "worse camera's error after (mm)"}
    name = "touch calibration (dtx calibrate touches)"
    truth = scene_camera_truth(DatasetReader(ws.collected).info.scene)
    if truth is None:
        return [point(PIPELINE, name, float("nan"), None, **extra, missing="the scene offsets no camera")]
    before = max(
        pose_error(np.asarray(world), truth[frame])[0] for frame, world in _given_extrinsics(ws.collected).items()
    )
    try:
        calibration, cpu_s = ws.touch_calibration
    except TouchCalibrationError as err:
        return [point(PIPELINE, name, float("nan"), None, **extra, refused=str(err))]
    after = max(row["error_mm"] for row in calibration.report(truth)["cameras"].values())
    return [point(PIPELINE, name, cpu_s, after, **extra, note=f"{before:.3g} mm before")]


def _test_maps(ws: Workspace) -> np.ndarray:
    """The depth-maps (N x H x W, m) the first session recorded for its test split, in its order."""
    return ws.first_test.depth_maps(ws.sessions)


def _training(ws: Workspace) -> Point:
    """The default model's epochs and its serving fit (CPU s, as the workspace logged them when it
    trained them; a fit an older workspace did not time is said, not guessed), beside what it
    serves on the session's test split: the ratio ``dtx evaluate`` reports for it."""
    model = ws.session_model()
    generator, depth_range_m = load_generator(model / "checkpoint.pt")
    served = predict_served(generator, _test_maps(ws), depth_range_m)[0]
    extra: dict[str, Any] = {
        "per": SESSION,
        "unit": "CPU s",
        "buys": f"served model's ratio on the session's test split (serves {generator.serves})",
    }
    try:
        serving_s = json.loads((model / "serving_cpu_s.json").read_text())
    except FileNotFoundError:
        serving_s, extra["note"] = 0.0, "epochs only: the serving fit was not timed (no serving_cpu_s.json)"
    seconds = sum(epoch_cpu_s(model)) + serving_s
    return point(
        PIPELINE, "training (epochs + serving fit)", seconds, dissimilarity_ratio(ws.first_test, served), **extra
    )


def _regions(ws: Workspace) -> list[Point]:
    """A planner's region through the default model as the inference node serves it (one
    thread, eager fp32 on the CPU; benchmarks._serve_stages): CPU s a region of each stage on the
    session's test grasps (each object's model cloud cut as the session's patch extractor cuts
    it, at the gels where the session held them), beside the figure of what that stage outputs."""
    generator, depth_range_m = load_generator(ws.session_model() / "checkpoint.pt")
    reader = DatasetReader(ws.session)
    params, scene = depth_map_params(reader)
    geometry, test = scene.gripper_geometry(), ws.first_test
    threads, cv_threads = torch.get_num_threads(), cv2.getNumThreads()
    costs, maps = [], np.empty((len(test.records), *test.truth.shape[1:3]), np.float32)
    try:  # served_network sets this process's threads as the node's
        line = f"(ngf {generator.config.ngf}, eager fp32, cpu)"
        network, split, _ = served_network(generator, depth_range_m, line, generator.serves, 1, MAX_BATCH)
        registered = {r.object_name: np.array(r.model_to_world) for r in test.records}
        # The gels in each object's frame (as a planner sends a cloud in its own), centred
        # between the fingers as the session's patch extractor centred them.
        model_to_gel = poses_at(test.records, registered, scene, params)
        for name in sorted(registered):
            rows = [i for i, r in enumerate(test.records) if r.object_name == name]
            poses = np.stack([np.linalg.inv(model_to_gel[test.records[i].sample_id][0]) for i in rows])
            index = model_index(scene, name)
            ms = stage_costs(index, None, poses, geometry, params, generator, depth_range_m, network, split.input_threads, REPEATS)  # fmt: skip
            costs.append((len(rows), ms))
            maps[rows] = contact_depth_maps(index, np.eye(4), poses, geometry, params, allow_empty=True).depth_maps_m
    finally:
        torch.set_num_threads(threads)
        cv2.setNumThreads(cv_threads)
    figures = _region_figures(ws, generator, depth_range_m, maps)
    return region_points(costs, figures)


def _region_figures(
    ws: Workspace, generator: UNetGenerator, depth_range_m: tuple[float, float], maps: np.ndarray
) -> dict[str, tuple[float | None, str]]:
    """What each region stage outputs, scored on the session's test truth: the cut's maps through
    the GelSight renderer, the prior's images and the served images (dissimilarity ratios), and the
    served uncertainty's Pearson r with the pixel error (as the uncertainty sweep scores it)."""
    test = ws.first_test
    reader = DatasetReader(ws.session)
    x = network_input(maps, depth_range_m, generator.config, generator.prior)
    served, uncertainty = predict_served(generator, maps, depth_range_m)
    cut = renderer_ratio(test, depth_map_params(reader)[1], reader.info.depth_crop_m, maps)["renderer_ratio"]
    prior = dissimilarity_ratio(test, to_uint8_rgb(prior_images(generator, x))) if generator.config.prior else None
    r = None
    if uncertainty is not None:
        r = uncertainty_statistics(uncertainty, served, test.truth, 1 - ssim_rgb(test.truth, served))["pearson_pixel"]
    return {
        "cut": (cut, "renderer ratio of the cut's maps"),
        "prior": (prior, "the physics prior's ratio"),
        "network": (dissimilarity_ratio(test, served), f"served image's ratio (serves {generator.serves})"),
        "uncertainty": (None if r is None else round(r, 4), "Pearson r of uncertainty with pixel error"),
    }


def region_points(
    costs: list[tuple[int, dict[str, float]]], figures: dict[str, tuple[float | None, str]]
) -> list[Point]:
    """One row per region stage (``figures``: its figure and what that is, by stage): its CPU s
    a region, from ``costs`` (per request: its regions and benchmarks._serve_stages.stage_costs'
    CPU ms a region) averaged over all regions. A stage no request timed (a checkpoint without
    uncertainty) says so."""
    regions = sum(n for n, _ in costs)
    points = []
    for stage, (figure, buys) in figures.items():
        extra = {"per": REGION, "unit": "CPU s", "buys": buys}
        key = f"{stage}_cpu_ms"
        if not costs or any(key not in ms for _, ms in costs):
            points.append(point(PIPELINE, stage, float("nan"), None, **extra, missing=f"no {stage} in what is served"))
        else:
            points.append(point(PIPELINE, stage, sum(n * ms[key] for n, ms in costs) / regions * 1e-3, figure, **extra))
    return points
