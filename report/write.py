"""report.md, one PNG per sweep (accuracy against time, Pareto front drawn) and points.json."""

from __future__ import annotations

import json
import math
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from report.defaults import default_line, project_default
from report.pareto import pareto_front, recommend
from report.pipeline import PIPELINE, pipeline_section
from report.specs import SPECS, Spec

PARETO_MARK = "◆"
DEFAULT_MARK = "**recommended**"
PROJECT_MARK = "✓"


def annotate(points: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Copies of the points with ``pareto`` and ``recommended`` set, sweep by sweep."""
    out = []
    for sweep, spec in SPECS.items():
        mine = [dict(p) for p in points if p["sweep"] == sweep]
        if not mine:
            continue
        pairs = [(p["time"], spec.score(p["accuracy"])) for p in mine]
        chosen = _informative_choice(spec, mine) if spec.informative else recommend(pairs, spec.tolerance)
        if spec.realism and _spread(spec, mine) > spec.tolerance:
            chosen = next((i for i, p in enumerate(mine) if p["setting"] == "all"), chosen)
        for index, (point, on_front) in enumerate(zip(mine, pareto_front(pairs))):
            point.update(pareto=on_front, recommended=index == chosen)
        out += mine
    return out


INFORMATIVE_P = 0.05


def _informative(point: dict[str, Any]) -> bool:
    p = point.get("p_vs_no_contact")
    return p is not None and not math.isnan(p) and p < INFORMATIVE_P


def _informative_choice(spec: Spec, points: Sequence[dict[str, Any]]) -> int | None:
    """The recommendation among the settings whose estimates beat the empty map's. When none
    does, no setting earns its time: the pipeline's own setting (``spec.pipeline_setting``) stays."""
    eligible = [i for i, p in enumerate(points) if _informative(p)]
    if eligible:
        chosen = recommend([(points[i]["time"], spec.score(points[i]["accuracy"])) for i in eligible], spec.tolerance)
        return None if chosen is None else eligible[chosen]
    return next((i for i, p in enumerate(points) if p["setting"] == spec.pipeline_setting), None)


def _spread(spec: Spec, points: Sequence[dict[str, Any]]) -> float:
    """Best minus worst score: how much the setting changes the accuracy."""
    scores = [spec.score(p["accuracy"]) for p in points if not math.isnan(p["accuracy"])]
    return max(scores) - min(scores) if scores else 0.0


def dumps(points: Sequence[dict[str, Any]]) -> str:
    """Strict JSON: a failed measurement (NaN) is written as null."""
    clean = [{k: None if isinstance(v, float) and math.isnan(v) else v for k, v in p.items()} for p in points]
    return json.dumps(clean, indent=1, allow_nan=False) + "\n"


def loads(text: str) -> list[dict[str, Any]]:
    """Points written by :func:`dumps`, a null accuracy back to NaN."""
    return [{**p, "accuracy": math.nan if p["accuracy"] is None else p["accuracy"]} for p in json.loads(text)]


def _format(value: Any) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def reason(spec: Spec, points: Sequence[dict[str, Any]]) -> str:
    """Why the recommended point: its figures next to the most accurate and fastest points."""
    chosen = next((p for p in points if p["recommended"]), None)
    if chosen is None:
        return "no setting gave a valid measurement."
    valid = [p for p in points if not math.isnan(p["accuracy"])]
    best = max(valid, key=lambda p: spec.score(p["accuracy"]))
    if spec.realism and _spread(spec, points) > spec.tolerance:
        worst = min(valid, key=lambda p: spec.score(p["accuracy"]))
        plain = min(valid, key=lambda p: p["time"])
        return (
            f"**{chosen['setting']}** — with {worst['setting']} the {spec.accuracy} is "
            f"{_format(worst['accuracy'])} "
            f"against {_format(best['accuracy'])} with {best['setting']}: figures measured without the effects "
            f"would not hold on real data, and simulating them costs {_format(chosen['time'])} instead of "
            f"{_format(plain['time'])} {spec.time}."
        )
    left_out = ""
    if spec.informative:
        uninformative = [p["setting"] for p in valid if not _informative(p)]
        valid = [p for p in valid if _informative(p)]
        if uninformative:
            left_out = (
                f" Left out: {', '.join(uninformative)} — the model's estimates from these maps do not beat "
                f"its estimate from an empty map on the contact windows (one-sided Wilcoxon p ≥ "
                f"{INFORMATIVE_P:g}), so their speed comes from dropping the contact."
            )
        if not valid:
            return (
                f"**{chosen['setting']}**, the pipeline's own — in no row do the model's estimates beat its "
                f"estimate from an empty map on the contact windows (one-sided Wilcoxon p < {INFORMATIVE_P:g}), "
                "so no setting earns its time or its savings: the model, not this setting, limits the "
                "accuracy here. Measure again with a model that uses the contact."
            )
        best = max(valid, key=lambda p: spec.score(p["accuracy"]))
    text = (
        f"**{chosen['setting']}** — {spec.accuracy} {_format(chosen['accuracy'])} at "
        f"{_format(chosen['time'])} {spec.time}: the fastest Pareto setting within {spec.tolerance:g} of the "
        f"best {spec.accuracy} ({_format(best['accuracy'])}, {best['setting']})"
    )
    if best is not chosen and chosen["time"] > 0:
        text += f", which takes {best['time'] / chosen['time']:.2g}x as long"
    return text + "." + left_out


def table(spec: Spec, points: Sequence[dict[str, Any]], project: str | None = None) -> str:
    """The sweep's table; ``project`` is the row label of the project's default setting. An extra
    no point has (one a sweep gives only in some runs: PER_SESSION) is no column."""
    extras = [(key, title) for key, title in spec.extras if any(key in p for p in points)]
    header = [
        spec.setting,
        spec.accuracy,
        spec.time,
        *(title for _, title in extras),
        "Pareto",
        "recommended",
        "project default",
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for p in points:
        cells = [
            p["setting"],
            _format(p["accuracy"]),
            _format(p["time"]),
            *(_format(p.get(key)) for key, _ in extras),
            PARETO_MARK if p["pareto"] else "",
            DEFAULT_MARK if p["recommended"] else "",
            PROJECT_MARK if p["setting"] == project else "",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(spec: Spec, points: Sequence[dict[str, Any]], path: Path) -> None:
    import matplotlib  # noqa: PLC0415 (only writing a report needs it)

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt  # noqa: PLC0415 - matplotlib loads only to draw a figure

    valid = [p for p in points if not math.isnan(p["accuracy"])]
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    ax.scatter([p["time"] for p in valid], [p["accuracy"] for p in valid], color="grey", label="setting")
    front = sorted((p for p in valid if p["pareto"]), key=lambda p: p["time"])
    ax.plot([p["time"] for p in front], [p["accuracy"] for p in front], "o-", color="tab:blue", label="Pareto front")
    for i, p in enumerate(sorted(valid, key=lambda p: p["time"])):
        # Labels alternate above and below, in order of time: settings of one accuracy sit side by side.
        offset = (3, 3) if i % 2 == 0 else (3, -9)
        ax.annotate(p["setting"], (p["time"], p["accuracy"]), fontsize=6, xytext=offset, textcoords="offset points")
        if p["recommended"]:
            ax.scatter(
                [p["time"]], [p["accuracy"]], s=160, facecolors="none", edgecolors="tab:red", label="recommended"
            )
    times = [p["time"] for p in valid if p["time"] > 0]
    if times and max(times) / min(times) > 5:
        ax.set_xscale("log")
    _span_at_least(ax, [p["accuracy"] for p in valid], spec.tolerance)
    ax.set_xlabel(spec.time)
    ax.set_ylabel(spec.accuracy + ("" if spec.higher_is_better else " (lower is better)"))
    ax.set_title(textwrap.fill(spec.title, 60), fontsize=10)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _span_at_least(ax: Any, accuracies: Sequence[float], tolerance: float) -> None:
    """The accuracy axis spans at least twice the table's tolerance, in plain numbers: settings
    whose accuracies differ by less than a lab would notice are drawn level, not stretched across
    the plot by an axis of 1e-8 steps."""
    ax.ticklabel_format(axis="y", useOffset=False, style="plain")
    if not accuracies:
        return
    low, high = min(accuracies), max(accuracies)
    if high - low < 2 * tolerance:
        middle = (low + high) / 2
        ax.set_ylim(middle - tolerance, middle + tolerance)


def write_report(out: Path, points: Sequence[dict[str, Any]], header: Sequence[str]) -> Path:
    """Write report.md, <sweep>.png and points.json under ``out``; ``header`` lines (mode,
    duration, what was reduced) open the report. Returns the report's path."""
    out.mkdir(parents=True, exist_ok=True)
    marked = annotate(points)
    lines = [
        "# What accuracy costs in time",
        "",
        *header,
        "",
        *pipeline_section(points),
        f"In every table {PARETO_MARK} marks a Pareto-optimal setting (no other setting is both at least as "
        f"fast and at least as accurate, and better in one), {DEFAULT_MARK} the recommended one (the fastest "
        f"Pareto setting within the table's tolerance of the best) and {PROJECT_MARK} the setting the "
        "project runs by default. Every measured point is in points.json.",
        "",
    ]
    for sweep, spec in SPECS.items():
        mine = [p for p in marked if p["sweep"] == sweep]
        if not mine:
            continue
        plot(spec, mine, out / f"{sweep}.png")
        lines += [
            f"## {spec.title}",
            "",
            spec.question,
            "",
            table(spec, mine, project_default(sweep, mine)),
            "",
            "Recommended: " + reason(spec, mine),
            "",
            default_line(sweep, mine),
            "",
            f"![{spec.title}]({sweep}.png)",
            "",
        ]
    # annotate() keeps only the sweeps of SPECS; the pipeline's rows (no Pareto front) are kept as measured.
    (out / "points.json").write_text(dumps([*marked, *(p for p in points if p["sweep"] == PIPELINE)]))
    path = out / "report.md"
    path.write_text("\n".join(lines))
    return path
