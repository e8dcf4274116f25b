"""``dtx evaluate CHECKPOINT SESSION SESSION ...``: the paper's analysis over several sessions.

The pairs evaluated are each session's part of the sessions' joint split (models.sessions:
the split the model was trained with, when it was trained on the same sessions). The whole
set is analysed as one dataset is (models.evaluate), and each session on its own: its SSIM
against a baseline drawn from its own ground truths (models.evaluate.SUMMARY_KEYS).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from models.evaluate import SUMMARY_KEYS, full_analysis, ssim_statistics
from models.networks import ModelConfigError, UNetGenerator
from models.predictions import Predictions, joined, predict_records
from models.sessions import PathLike, open_sessions, session_records


def evaluate_sessions(
    generator: UNetGenerator,
    depth_range_m: tuple[float, float],
    roots: Sequence[PathLike],
    split: str = "test",
    hold_out_object: str = "",
    density: Sequence[float] = (),
    baseline_draws: int = 15,
    template_px: int = 32,
    seed: int = 0,
) -> tuple[dict[str, Any], Predictions]:
    """models.evaluate.evaluate's result for the sessions' pairs together, with ``sessions``:
    per session (by name) its path, fingerprint and SSIM summary (or, with fewer than 2 pairs,
    its count alone). Sample ids are ``SESSION/SAMPLE``. The density table takes one session."""
    if density:
        raise ModelConfigError("--density makes one session's depth-maps again: evaluate one session at a time")
    sessions = open_sessions(roots, depth_range_m)
    chosen = session_records(sessions, split, hold_out_object)
    parts, ids, per_session = [], [], {}
    for session, records in zip(sessions, chosen):
        per_session[session.name] = {
            "path": str(session.reader.root.resolve()),
            "fingerprint": session.fingerprint,
            "n": len(records),
        }
        if not records:
            continue
        part = predict_records(generator, depth_range_m, session.reader, records, session.name, least=1)
        parts.append(part)
        ids += [f"{session.name}/{sample_id}" for sample_id in part.sample_ids]
        if len(records) >= 2:
            summary = ssim_statistics(part.truth, part.estimate, baseline_draws, seed)
            per_session[session.name] |= {k: v for k, v in summary.items() if k in SUMMARY_KEYS}
    if sum(len(p.sample_ids) for p in parts) < 2:
        raise ModelConfigError(f"the {split} split of the {len(sessions)} sessions has fewer than 2 samples")
    predictions = joined(parts, ids)
    result = full_analysis(predictions, baseline_draws, template_px, seed)
    result["density"] = []
    result["sessions"] = per_session
    result.update({"split": split, "hold_out_object": hold_out_object, "sample_ids": ids})
    return result, predictions


def sessions_table(result: dict[str, Any]) -> str:
    """A line a session of :func:`evaluate_sessions`'s result: its SSIM against its baseline."""
    lines = ["per session (the figures above are the whole):"]
    for name, row in result["sessions"].items():
        if "ssim_model_mean" in row:
            lines.append(
                f"{'  ' + name:28s}{row['ssim_model_mean']:>13.4f} / {row['ssim_baseline_mean']:.4f}  "
                f"ratio {row['dissimilarity_ratio']:.3f}, {row['n']} pairs"
            )
        else:
            lines.append(f"{'  ' + name:28s}{row['n']} pair(s): too few for statistics")
    return "\n".join(lines)
