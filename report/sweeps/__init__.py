"""The measurements behind the accuracy-time report. Each sweep returns points
``{"sweep", "setting", "time", "accuracy", ...extra figures}``; what "time" and "accuracy"
mean for a sweep is in report.specs. The work is done by the project's own code (a collection
session on the simulated scene, dataset.redepth, dataset.synth contacts, models.train,
perception, sim, benchmarks), on the datasets and models of a report.workspace; this module
only chooses settings.

The session sweeps (resolution, density, depth-map rule, pose uncertainty) run on a collected
session, since what they change is how the patch extractor makes depth-maps from registered
models, or what the served model is told of their pose error; the other learned sweeps compare
networks and GelSight effects on analytic contacts, whose ground truth can be rendered again.
The serving sweeps (the uncertainty's method, what serves) score the session model through the
served path on the session's test split, as a planner receives its answers.
"""

from __future__ import annotations

from collections.abc import Callable

from report.specs import Point
from report.sweeps.calibration import calibration_grasps
from report.sweeps.learned import gelsight_effects, inference, training_length, width
from report.sweeps.pipeline import pipeline
from report.sweeps.registration import depth_effects, registration
from report.sweeps.serving import serving, uncertainty
from report.sweeps.session import density, depth_map, pose_sigma, resolution
from report.workspace import Workspace

SWEEPS: dict[str, Callable[[Workspace], list[Point]]] = {
    "resolution": resolution,
    "training_length": training_length,
    "width": width,
    "density": density,
    "depth_map": depth_map,
    "pose_sigma": pose_sigma,
    "gelsight_effects": gelsight_effects,
    "uncertainty": uncertainty,
    "serving": serving,
    "inference": inference,
    "registration": registration,
    "depth_effects": depth_effects,
    "calibration_grasps": calibration_grasps,
    "pipeline": pipeline,
}
