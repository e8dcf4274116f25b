"""The accuracy-time report's first section, "What each second buys": what a grasp costs stage
by stage, what a session costs to calibrate and to train, and what a planner's region costs to
serve, each beside the measured figure it buys. The rows are measured by
report.sweeps.pipeline; this module holds what needs neither torch nor Open3D (the command line
writes the report without them): the grasp's stages as the collector times them, the rows made
from a session's session.json, and the section's table.

These rows are not a sweep of one setting against another: there is no Pareto front among an
arm move and a training run, so report.write leaves them out of its per-sweep tables."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from report.specs import Point, point

PIPELINE = "pipeline"
GRASP, SESSION, REGION = "grasp", "session", "region"

# Each stage nodes.collector.CollectorNode.try_grasp times (session.json "stage_median_ms"),
# as the issue groups the workcell, and what it buys. The stages overlap: the cut runs beside
# the capture ("depth_maps" is only what outlasts it) and the release beside the write, so a
# grasp's wall time is less than their sum (the "whole grasp" row).
GRASP_STAGES: tuple[tuple[str, str, str], ...] = (
    ("register", "cameras + registration (register)", "registration ADD-S median vs the scene's poses (mm)"),
    ("approach", "arm: approach, fingers opening beside (approach)", "the gels at the drawn pose (no figure)"),
    ("close", "gripper: close to the grip (close)", "the held contact (no figure)"),
    ("capture", "GelSight: frame after settling, cut beside it (capture)", "the ground truth itself (no figure)"),
    ("depth_maps", "cut: depth-maps, beyond the capture (depth_maps)", "renderer ratio of the session's maps"),
    ("write", "writing: both pairs (write)", "dataset check problems (0: nothing lost)"),
    ("release", "arm: release and lift, beside the write (release)", "the next grasp's start (no figure)"),
)
# The registration runs once per object and the collector keeps its pose, so most grasps'
# "register" is a dictionary look-up: the median hides the registration's own time.
REGISTER_NOTE = "once per object; the median grasp reuses the pose"
WHOLE_GRASP = "whole grasp (the dataset's pace; stages overlap)"
# The table's time units: its rows run from minutes of training to microseconds of a region's stage.
DURATION_UNITS: tuple[tuple[float, str], ...] = ((1.0, "s"), (1e-3, "ms"), (1e-6, "µs"))


def grasp_points(summary: Mapping[str, Any] | None, figures: Mapping[str, float | None]) -> list[Point]:
    """One point per collector stage (seconds a grasp: its median), from a session's session.json
    ``summary`` (None: the file is absent); ``figures``:
    each stage's measured figure by stage name (GRASP_STAGES says what it is). A stage that
    ``summary`` does not time (a session resumed after its last grasp writes none, an older
    collector) gets a NaN time and a ``missing`` extra saying so, never an estimate."""
    medians = (summary or {}).get("stage_median_ms") or {}
    points = []
    for stage, name, buys in GRASP_STAGES:
        extra: dict[str, Any] = {"per": GRASP, "unit": "s", "buys": buys}
        if stage == "register":
            extra["note"] = REGISTER_NOTE
        if stage in medians:
            seconds = float(medians[stage]) * 1e-3
        else:
            seconds = math.nan
            extra["missing"] = _missing(summary, "stage_median_ms." + stage)
        points.append(point(PIPELINE, name, seconds, figures.get(stage), **extra))
    return points


def _missing(summary: Mapping[str, Any] | None, field: str) -> str:
    if summary is None:
        return "the session has no session.json (still running, or stopped before its end)"
    return f"session.json has no {field} (a resumed session times only the grasps it collected)"


INTRO = (
    "What the pipeline spends and what each part buys: a grasp's stages (the median grasp, as the "
    "collector timed them; the cut runs beside the capture and the release beside the write), a "
    "session's calibration and training (CPU s), and a planner's region through the served model "
    "(CPU s a region). A ratio is the estimate's dissimilarity 1 - SSIM over that of a random test "
    "image (models.evaluate.ssim_statistics): below 1 the figure beats guessing, 0 is the truth."
)


def pipeline_section(points: Sequence[Point]) -> list[str]:
    """report.md's lines for the pipeline points among ``points`` (none: no lines): a table of
    stage, per what, its time (report.pipeline._duration), what it buys and the figure, in the order
    measured."""
    mine = [p for p in points if p["sweep"] == PIPELINE]
    if not mine:
        return []
    lines = [
        "## What each second buys",
        "",
        INTRO,
        "",
        "| stage | per | time | what it buys | figure |",
        "|---|---|---|---|---|",
    ]
    for p in mine:
        buys = p.get("buys", "")
        for key in ("note", "missing", "refused"):
            if p.get(key):
                buys += f" — {'not measured: ' if key != 'note' else ''}{p[key]}"
        time = _duration(p["time"], p.get("unit", "s"))
        cells = [p["setting"], p.get("per", ""), time, buys, _figure(p["accuracy"])]
        lines.append("| " + " | ".join(str(cell) for cell in cells) + " |")
    return lines + [""]


def _duration(seconds: float | None, unit: str) -> str:
    """A time in seconds as the table prints it: in the largest of s, ms and µs that keeps it at 1
    or more (µs below that), 4 significant figures, "CPU" kept where ``unit`` is "CPU s"; a dash
    where it was not measured."""
    if seconds is None or math.isnan(seconds):
        return "–"
    prefix = unit.removesuffix("s")  # "CPU " or ""
    if seconds == 0:
        return f"0 {prefix}s"
    scale, name = next(((s, n) for s, n in DURATION_UNITS if abs(seconds) >= s), DURATION_UNITS[-1])
    return f"{seconds / scale:.4g} {prefix}{name}"


def _figure(value: float | None) -> str:
    """A figure as the tables print it; not measured (None after points.json, NaN) as a dash."""
    if value is None or math.isnan(value):
        return "–"
    return f"{value:.4g}"
