"""The figures of ``dtx evaluate --figures DIR``: qualitative.png, ssim_bars.png and density.png
drawn from :func:`models.evaluate.evaluate`'s result and predictions."""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Any

import numpy as np

from models.evaluate import PAPER_DENSITY_SSIM
from models.predictions import Predictions
from workcell.scene import SceneError, load_scene


def write_figures(
    result: dict[str, Any],
    predictions: Predictions,
    depth_range_m: tuple[float, float],
    out: str | os.PathLike[str],
    rows: int = 8,
) -> list[Path]:
    """qualitative.png (object, depth-map, truth with template box in blue, estimate with
    matched box in red), ssim_bars.png (model vs baseline, standard-error bars) and, when
    the result has a density table, density.png. Returns the written paths."""
    import matplotlib  # noqa: PLC0415 (only evaluation with --figures needs it)

    matplotlib.use("Agg")
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    count = min(rows, len(predictions.sample_ids))
    written = [
        _qualitative_figure(result, predictions, depth_range_m, count, out_dir / "qualitative.png"),
        _ssim_bars_figure(result, out_dir / "ssim_bars.png"),
    ]
    if result["density"]:
        written.append(_density_figure(result["density"], out_dir / "density.png"))
    return written


def _save(fig: Any, path: Path) -> Path:
    from matplotlib import pyplot as plt  # noqa: PLC0415 - matplotlib loads only to draw a figure

    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _qualitative_figure(
    result: dict[str, Any], predictions: Predictions, depth_range_m: tuple[float, float], count: int, path: Path
) -> Path:
    """The first ``count`` pairs, one row each: object, depth-map, truth, estimate."""
    from matplotlib import patches  # noqa: PLC0415 - matplotlib loads only to draw a figure
    from matplotlib import pyplot as plt  # noqa: PLC0415 - matplotlib loads only to draw a figure

    size = result["template_match"]["template_px"]
    fig, axes = plt.subplots(count, 4, figsize=(8, 2 * count), squeeze=False)
    for row, ax in enumerate(axes):
        match = result["template_match"]["per_sample"][row]
        _draw_object(ax[0], predictions, row)
        ax[1].imshow(
            np.nan_to_num(predictions.depth_maps_m[row], nan=depth_range_m[1]) * 1e3,
            cmap="viridis",
            vmin=depth_range_m[0] * 1e3,
            vmax=depth_range_m[1] * 1e3,
        )
        ax[2].imshow(predictions.truth[row])
        ax[2].add_patch(patches.Rectangle(match["template_xy"], size, size, fill=False, color="blue"))
        ax[3].imshow(predictions.estimate[row])
        if match["match_xy"] is not None:  # a flat template has no match
            ax[3].add_patch(patches.Rectangle(match["match_xy"], size, size, fill=False, color="red"))
        ax[3].set_xlabel(f"SSIM {result['ssim_model'][row]:.3f}, match {match['score']:.2f}", fontsize=7)
        for a in ax:
            a.set_xticks([])
            a.set_yticks([])
    for a, title in zip(axes[0], ("object", "depth-map (mm)", "ground truth", "estimate")):
        a.set_title(title, fontsize=9)
    return _save(fig, path)


def _ssim_bars_figure(result: dict[str, Any], path: Path) -> Path:
    """Model against baseline SSIM, standard-error bars."""
    from matplotlib import pyplot as plt  # noqa: PLC0415 - matplotlib loads only to draw a figure

    fig, ax = plt.subplots(figsize=(3, 3.5))
    ax.bar(
        ["baseline", "model"],
        [result["ssim_baseline_mean"], result["ssim_model_mean"]],
        yerr=[result["ssim_baseline_se"], result["ssim_model_se"]],
        capsize=6,
        color=["grey", "tab:blue"],
    )
    ax.set_ylabel("SSIM (mean ± s.e.)")
    ax.set_ylim(0, 1)
    ax.set_title(f"ratio {result['dissimilarity_ratio']:.2f}, p {result['p_value_wilcoxon']:.1e}", fontsize=9)
    return _save(fig, path)


def _density_figure(density_rows: list[dict[str, Any]], path: Path) -> Path:
    """SSIM against point-cloud density, this model's beside the paper's."""
    from matplotlib import pyplot as plt  # noqa: PLC0415 - matplotlib loads only to draw a figure

    fig, ax = plt.subplots(figsize=(4, 3))
    ax.errorbar(
        [r["points_per_cm3"] for r in density_rows],
        [r["ssim_mean"] for r in density_rows],
        yerr=[r["ssim_se"] for r in density_rows],
        marker="o",
        capsize=4,
        label="this model",
    )
    paper = sorted(PAPER_DENSITY_SSIM.items())
    ax.plot([d for d, _ in paper], [v for _, v in paper], "s--", color="grey", label="paper")
    ax.set_xscale("log")
    ax.set_xlabel("point-cloud density (points/cm³)")
    ax.set_ylabel("SSIM")
    ax.legend(fontsize=8)
    return _save(fig, path)


def _draw_object(ax: Any, predictions: Predictions, row: int) -> None:
    """The object as the gel saw it: its model's points in the gel frame (x right, z down, as
    the depth-map), the near side only, shaded by distance, and the depth-map's crop; or the
    sample's name where the dataset does not say where the gel was."""
    from matplotlib import patches  # noqa: PLC0415 - matplotlib loads only to draw a figure

    label = f"{predictions.objects[row]}\n{predictions.sample_ids[row]}"
    model_to_gel = predictions.model_to_gel[row] if predictions.model_to_gel else None
    cloud = _model_cloud(predictions.scene, predictions.objects[row]) if model_to_gel is not None else None
    if model_to_gel is None or cloud is None or predictions.depth_crop_m is None:
        ax.text(0.5, 0.5, label, ha="center", va="center", fontsize=7)
        return
    points_mm = (cloud @ model_to_gel[:3, :3].T + model_to_gel[:3, 3]) * 1e3
    near = points_mm[points_mm[:, 1] < np.median(points_mm[:, 1])]
    near = near[np.argsort(-near[:, 1])]  # nearest drawn last, on top
    ax.scatter(near[:, 0], near[:, 2], c=near[:, 1], s=0.5, cmap="Greys")
    crop_x, _, crop_z = (v * 1e3 for v in predictions.depth_crop_m)
    ax.add_patch(patches.Rectangle((-crop_x / 2, -crop_z / 2), crop_x, crop_z, fill=False, color="tab:orange"))
    ax.set_aspect("equal")
    ax.invert_yaxis()
    ax.set_xlabel(label.replace("\n", " "), fontsize=6)


@functools.lru_cache(maxsize=16)
def _model_cloud(scene: str, object_name: str) -> np.ndarray | None:
    """The 2 mm model cloud of ``object_name`` in ``scene`` (None: not a mesh of that scene)."""
    from perception.registration import sample_model_cloud  # noqa: PLC0415 - Open3D loads only to sample a mesh

    try:
        mesh = load_scene(scene).mesh(object_name)
    except (SceneError, OSError):
        return None
    return sample_model_cloud(mesh).points_m
