"""The measurements behind the accuracy-time report. Each sweep returns points
``{"sweep", "setting", "time", "accuracy", ...extra figures}``; what "time" and "accuracy"
mean for a sweep is in report.specs. The work is done by the project's own code (a collection
session on the simulated scene, dataset.redepth, dataset.synth contacts, models.train,
perception, sim, benchmarks), on the datasets and models of a report.workspace; this module
only chooses settings.

The density and resolution sweeps run on a collected session, since what they change is how
the patch extractor makes depth-maps from registered models; the other learned sweeps compare
networks and GelSight effects on analytic contacts, whose ground truth can be rendered again.
"""

from __future__ import annotations

from collections.abc import Callable

from report.specs import Point
from report.sweeps.calibration import calibration_grasps
from report.sweeps.learned import dropout, gelsight_effects, inference, training_length, width
from report.sweeps.registration import depth_effects, registration
from report.sweeps.session import density, resolution
from report.workspace import Workspace

SWEEPS: dict[str, Callable[[Workspace], list[Point]]] = {
    "resolution": resolution,
    "training_length": training_length,
    "width": width,
    "density": density,
    "gelsight_effects": gelsight_effects,
    "dropout": dropout,
    "inference": inference,
    "registration": registration,
    "depth_effects": depth_effects,
    "calibration_grasps": calibration_grasps,
}
