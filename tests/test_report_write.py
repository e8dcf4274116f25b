"""report.write on a small fixed set of points: tables carry the Pareto, recommended and project
default marks, plots and points.json are written, effects sweeps recommend realism when it
matters, and a default the report does not recommend is explained or flagged."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from perception.registration import RegistrationParams
from report.defaults import PROJECT_DEFAULTS, WHY_NOT, default_line, project_default
from report.specs import SPECS
from report.write import DEFAULT_MARK, PARETO_MARK, PROJECT_MARK, _span_at_least, annotate, dumps, loads, write_report

POINTS = [
    # 1 pts/cm³ is fast and within 0.01 of the best, but its estimates do not beat the model's
    # estimate from an empty map (p_vs_no_contact): it is no candidate.
    {
        "sweep": "density",
        "setting": "1 pts/cm³",
        "time": 0.2,
        "accuracy": 0.832,
        "points_median": 7,
        "p_vs_no_contact": 0.4,
    },
    {
        "sweep": "density",
        "setting": "40 pts/cm³",
        "time": 0.3,
        "accuracy": 0.835,
        "points_median": 70,
        "p_vs_no_contact": 0.001,
    },
    {
        "sweep": "density",
        "setting": "80 pts/cm³",
        "time": 0.5,
        "accuracy": 0.84,
        "points_median": 97,
        "p_vs_no_contact": 0.001,
    },
    {
        "sweep": "density",
        "setting": "unfiltered",
        "time": 1.0,
        "accuracy": 0.83,
        "points_median": 38000,
        "p_vs_no_contact": 0.002,
    },
    {"sweep": "registration_voxel", "setting": "4 mm", "time": 430.0, "accuracy": 2.0},
    {"sweep": "registration_voxel", "setting": "8 mm", "time": 170.0, "accuracy": 4.0},
    {"sweep": "registration_voxel", "setting": "10 mm", "time": 150.0, "accuracy": math.nan},
    {"sweep": "gelsight_effects", "setting": "none", "time": 1.4, "accuracy": 0.75},
    {"sweep": "gelsight_effects", "setting": "markers", "time": 1.8, "accuracy": 0.15},
    {"sweep": "gelsight_effects", "setting": "all", "time": 2.3, "accuracy": 0.14},
]


def _rows(report: str, title: str) -> dict[str, str]:
    section = report.split(f"## {title}")[1].split("\n## ")[0]
    return {
        line.split(" | ")[0].lstrip("| "): line
        for line in section.splitlines()
        if line.startswith("| ") and not line.startswith("| density |")
    }


def test_marks_front_and_default() -> None:
    marked = {(p["sweep"], p["setting"]): p for p in annotate(POINTS)}
    assert [marked["density", s]["pareto"] for s in ("1 pts/cm³", "40 pts/cm³", "80 pts/cm³", "unfiltered")] == [
        True,
        True,
        True,
        False,
    ]
    # 40 is within 0.01 SSIM of the best (80) and the fastest that beats an empty map: the default.
    assert marked["density", "40 pts/cm³"]["recommended"]
    # Lower ADD-S is better; a failed measurement is on no front.
    assert marked["registration_voxel", "4 mm"]["pareto"] and marked["registration_voxel", "8 mm"]["pareto"]
    assert not marked["registration_voxel", "10 mm"]["pareto"]
    assert marked["registration_voxel", "4 mm"]["recommended"]
    # Leaving markers out loses 0.6 SSIM: the effects are recommended although slower.
    assert marked["gelsight_effects", "all"]["recommended"]


def test_report_tables_plots_and_points(tmp_path: Path) -> None:
    path = write_report(tmp_path, POINTS, ["Mode: test"])
    report = path.read_text()
    assert "Mode: test" in report
    density = _rows(report, "Point-cloud density")
    assert PARETO_MARK in density["40 pts/cm³"] and DEFAULT_MARK in density["40 pts/cm³"]
    assert PARETO_MARK not in density["unfiltered"] and DEFAULT_MARK not in density["unfiltered"]
    assert DEFAULT_MARK not in density["80 pts/cm³"] and PARETO_MARK in density["80 pts/cm³"]
    assert "Recommended: **40 pts/cm³**" in report and "Left out: 1 pts/cm³" in report
    assert "Recommended: **all**" in report
    assert "| 10 mm | – |" in report
    for sweep in ("density", "registration_voxel", "gelsight_effects"):
        assert (tmp_path / f"{sweep}.png").read_bytes()[:4] == b"\x89PNG"
    saved = json.loads((tmp_path / "points.json").read_text())
    assert len(saved) == len(POINTS)
    assert {p["setting"] for p in saved if p["recommended"]} == {"40 pts/cm³", "4 mm", "all"}
    assert next(p for p in saved if p["setting"] == "10 mm")["accuracy"] is None


def test_no_setting_beating_an_empty_map_keeps_the_pipelines_own(tmp_path: Path) -> None:
    """When no depth-map setting helps the model, the fastest would merely drop the contact
    and the most accurate would win by noise: the pipeline's own setting stays, and the report
    says the model is what limits."""
    points = [{**p, "p_vs_no_contact": 0.3} for p in POINTS if p["sweep"] == "density"]
    marked = {p["setting"]: p for p in annotate(points)}
    assert [s for s, p in marked.items() if p["recommended"]] == ["unfiltered"]
    report = write_report(tmp_path, points, ["Mode: test"]).read_text()
    assert "Recommended: **unfiltered**, the pipeline's own — in no row do the model's estimates beat" in report


def test_points_round_trip_with_failed_measurements() -> None:
    again = loads(dumps(POINTS))
    assert math.isnan(again[6]["accuracy"])
    assert again[:6] == POINTS[:6]


def test_every_table_names_the_projects_default() -> None:
    assert set(SPECS) <= set(PROJECT_DEFAULTS)
    assert set(WHY_NOT) <= set(PROJECT_DEFAULTS)


def test_the_projects_default_is_marked_and_explained(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The voxel row the registration runs with by default is marked; it is not the recommended
    one here, so the report gives the recorded reason, and without one says that none is recorded
    instead of passing the default off as the recommended."""
    voxel = f"{RegistrationParams().voxel_size_m * 1e3:g} mm"
    points = [{**p, "setting": voxel} if p["setting"] == "8 mm" else p for p in POINTS]
    report = write_report(tmp_path, points, ["Mode: test"]).read_text()
    rows = _rows(report, "Registration voxel size")
    assert rows[voxel].endswith(f"| {PROJECT_MARK} |") and not rows["4 mm"].endswith(f"| {PROJECT_MARK} |")
    assert f"Project default: **{voxel}**, not the recommended: {WHY_NOT['registration_voxel']}." in report
    # The density table's default, unfiltered, is the pipeline's own, kept for a recorded reason.
    assert f"Project default: **unfiltered**, not the recommended: {WHY_NOT['density']}." in report
    monkeypatch.delitem(WHY_NOT, "registration_voxel")
    report = write_report(tmp_path, points, ["Mode: test"]).read_text()
    assert f"Project default: **{voxel}**, not the recommended **4 mm**: no reason is recorded" in report


def test_a_default_kept_for_a_reason_says_it_and_a_missing_one_says_not_measured() -> None:
    marked = annotate([p for p in POINTS if p["sweep"] == "gelsight_effects"])
    scene = project_default("gelsight_effects", marked)
    assert scene == "sensor_noise"  # what scenes/ycb_three.yaml calls for
    assert default_line("gelsight_effects", [*marked, {"setting": scene, "recommended": False}]) == (
        f"Project default: **{scene}**, not the recommended: {WHY_NOT['gelsight_effects']}."
    )
    marked = annotate([p for p in POINTS if p["sweep"] == "registration_voxel" and p["setting"] != "8 mm"])
    assert "(not among the settings measured here)" in default_line("registration_voxel", marked)


@pytest.mark.parametrize(
    ("accuracies", "tolerance", "limits"),
    [
        ([0.9141037, 0.91410375], 0.01, (0.90410373, 0.92410373)),  # level within 1e-8: drawn level
        ([0.80, 0.95], 0.01, None),  # a spread wider than the tolerance keeps matplotlib's limits
    ],
)
def test_a_plots_accuracy_axis_spans_the_tables_tolerance_in_plain_numbers(
    accuracies: list[float], tolerance: float, limits: tuple[float, float] | None
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    fig, ax = plt.subplots()
    ax.scatter([1.0, 2.0], accuracies)
    _span_at_least(ax, accuracies, tolerance)
    fig.canvas.draw()
    low, high = ax.get_ylim()
    if limits is None:
        assert low <= min(accuracies) and high >= max(accuracies) and high - low < 0.5
    else:
        assert (low, high) == pytest.approx(limits, abs=1e-7)
    assert ax.yaxis.get_offset_text().get_text() == ""  # no "1e-8 + 9.14e-1" above the axis
    plt.close(fig)
