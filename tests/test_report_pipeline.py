"""The report's "What each second buys" section (report.pipeline, report.sweeps.pipeline): its rows
from a session's stage times, what a missing time says, its place in report.md and points.json,
and the grasp and calibration rows measured on a real simulated session."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import pytest

from report.pipeline import GRASP_STAGES, PIPELINE, WHOLE_GRASP, _duration, grasp_points, pipeline_section
from report.plan import QUICK
from report.specs import point
from report.sweeps.pipeline import grasp_stages, touch_calibration
from report.workspace import Workspace
from report.write import dumps, loads, write_report

SUMMARY: dict[str, Any] = {
    "stats": {"grasps_done": 40, "pairs_written": 80},
    "wall_s": 17.39,
    "stage_median_ms": {
        "register": 0.0,
        "approach": 52.75,
        "close": 29.99,
        "capture": 78.46,
        "depth_maps": 0.01,
        "write": 26.59,
        "release": 43.76,
    },
}
FIGURES = {"register": 1.2, "depth_maps": 0.61, "write": 0.0}


def _made_up_points() -> list[dict[str, Any]]:
    """A grasp's rows from SUMMARY, a session row and a region row, as the sweep makes them."""
    return [
        *grasp_points(SUMMARY, FIGURES),
        point(PIPELINE, "training (epochs + serving fit)", 21.3, 0.52, per="session", unit="CPU s", buys="ratio"),
        point(PIPELINE, "network", 0.0023, 0.52, per="region", unit="CPU s", buys="served image's ratio"),
    ]


def _table_rows(lines: list[str]) -> list[list[str]]:
    return [[cell.strip() for cell in line.strip("|").split("|")] for line in lines if line.startswith("| ")][1:]


def test_the_section_renders_every_row_with_its_unit_and_figure() -> None:
    lines = pipeline_section(_made_up_points())
    assert lines[0] == "## What each second buys"
    rows = {row[0]: row for row in _table_rows(lines)}
    assert len(rows) == len(GRASP_STAGES) + 2  # every stage, training, a region stage
    assert rows["writing: both pairs (write)"][1:] == [
        "grasp",
        "26.59 ms",
        "dataset check problems (0: nothing lost)",
        "0",
    ]
    assert rows["training (epochs + serving fit)"][1:3] == ["session", "21.3 CPU s"]
    assert rows["network"][1:] == ["region", "2.3 CPU ms", "served image's ratio", "0.52"]
    assert rows["cameras + registration (register)"][2] == "0 s"  # the median grasp reuses its pose
    assert rows["arm: approach, fingers opening beside (approach)"][4] == "–"  # buys nothing measured
    assert "reuses the pose" in rows["cameras + registration (register)"][3]


@pytest.mark.parametrize(
    ("seconds", "unit", "shown"),
    [
        (437.3, "CPU s", "437.3 CPU s"),
        (1.0, "s", "1 s"),
        (0.08743, "s", "87.43 ms"),
        (1e-5, "s", "10 µs"),
        (3.095e-8, "CPU s", "0.03095 CPU µs"),
        (0.0, "s", "0 s"),
        (math.nan, "s", "–"),
        (None, "CPU s", "–"),
    ],
)
def test_a_time_is_shown_in_the_largest_unit_that_keeps_it_at_one_or_more(
    seconds: float | None, unit: str, shown: str
) -> None:
    assert _duration(seconds, unit) == shown


# None: no session.json; then as a session resumed after its last grasp writes it.
@pytest.mark.parametrize("summary", [None, {"stats": {"grasps_done": 40, "pairs_written": 0}, "stage_median_ms": {}}])
def test_a_session_without_stage_times_says_so_in_every_grasp_row(summary: dict[str, Any] | None) -> None:
    points = grasp_points(summary, FIGURES)
    assert all(math.isnan(p["time"]) and p["missing"] for p in points)
    expected = "no session.json" if summary is None else "session.json has no"
    assert all(expected in p["missing"] for p in points)
    rows = _table_rows(pipeline_section(points))
    assert all(row[2] == "–" and "not measured: " in row[3] for row in rows)


def test_points_round_trip_through_points_json() -> None:
    points = [*_made_up_points(), *grasp_points(None, {})]
    again = loads(dumps(points))
    assert pipeline_section(again) == pipeline_section(points)  # a NaN time comes back as null, shown alike
    assert [p["setting"] for p in again] == [p["setting"] for p in points]


def test_the_section_opens_the_report_and_its_points_are_kept(tmp_path: Path) -> None:
    other = [
        point("registration_voxel", f"{mm} mm", ms, add_s, add_s_mm_p90=add_s, accepted_rate=1.0)
        for mm, ms, add_s in ((2, 90.0, 1.0), (6, 30.0, 1.3))
    ]
    mine = _made_up_points()
    path = write_report(tmp_path, [*other, *mine], ["header line"])
    text = path.read_text()
    sections = [line for line in text.splitlines() if line.startswith("## ")]
    assert sections[0] == "## What each second buys" and len(sections) == 2
    assert not (tmp_path / f"{PIPELINE}.png").exists()  # no Pareto plot of unlike stages
    written = json.loads((tmp_path / "points.json").read_text())
    assert [p["setting"] for p in written if p["sweep"] == PIPELINE] == [p["setting"] for p in mine]
    assert sum(p["sweep"] == "registration_voxel" for p in written) == 2


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Workspace:
    """A workspace whose session the report collects as it collects its own (10 grasps)."""
    plan = dataclasses.replace(QUICK, session_grasps=10, seed=5)
    return Workspace(tmp_path_factory.mktemp("pipeline"), plan)


def test_a_real_sessions_grasp_and_calibration_rows(workspace: Workspace) -> None:
    ws = workspace
    grasp = {p["setting"]: p for p in grasp_stages(ws)}
    assert all(p["time"] >= 0 and "missing" not in p for p in grasp.values())  # a fresh session times them all
    assert grasp[WHOLE_GRASP]["accuracy"] == 2.0 and 0 < grasp[WHOLE_GRASP]["time"] < 60  # both fingers' pairs
    assert grasp["writing: both pairs (write)"]["accuracy"] == 0.0  # the dataset check found nothing
    assert 0 < grasp["cut: depth-maps, beyond the capture (depth_maps)"]["accuracy"] < 2
    assert 0 <= grasp["cameras + registration (register)"]["accuracy"] < 10  # ADD-S mm against the scene
    (calibration,) = touch_calibration(ws)
    # Ten grasps are too few touches to calibrate from: the row says why rather than a figure.
    assert math.isnan(calibration["time"]) and "needs >= 30" in calibration["refused"]
    rows = _table_rows(pipeline_section([*grasp.values(), calibration]))
    assert rows[-1][0] == "touch calibration (dtx calibrate touches)" and "not measured: " in rows[-1][3]
