"""What each sweep's "time" and "accuracy" are, how a table shows them and how close to the
best accuracy a setting must be to be recommended."""

from __future__ import annotations

import dataclasses
from typing import Any

# One measured setting of a sweep: {"sweep", "setting", "time", "accuracy", ...extra figures}.
Point = dict[str, Any]


def point(sweep: str, setting: str, time_value: float, accuracy: float | None, **extra: Any) -> Point:
    """A sweep's point; an accuracy of None (the setting failed) is NaN, never on a front."""
    return {
        "sweep": sweep,
        "setting": setting,
        "time": float(time_value),
        "accuracy": float("nan") if accuracy is None else float(accuracy),
        **extra,
    }


# Of several sessions (dtx report accuracy-time --session A B), each one's contact SSIM, in
# that order (report.sweeps.common.session_scores): a column only where a sweep ran on several.
PER_SESSION = "contact_ssim_per_session"
PER_SESSION_EXTRA = (PER_SESSION, "contact SSIM per session")

# The registration tables' columns beside the given cameras' ADD-S: the same registrations with
# the cameras as the session's touch calibration corrected them (report.sweeps.registration).
REGISTRATION_EXTRAS = (
    ("add_s_mm_p90", "ADD-S p90"),
    ("accepted_rate", "accepted"),
    ("add_s_mm_calibrated", "ADD-S touch-calibrated"),
    ("add_s_mm_p90_calibrated", "p90 touch-calibrated"),
)


@dataclasses.dataclass(frozen=True)
class Spec:
    title: str
    question: str
    setting: str
    time: str
    accuracy: str
    higher_is_better: bool
    # Recommended: the fastest Pareto setting within this much of the best accuracy; about
    # the spread of repeated measurements, so the margin is one a lab would not notice.
    tolerance: float
    extras: tuple[tuple[str, str], ...] = ()
    # Effects sweeps: the fastest setting (effects off) is never the advice when leaving an
    # effect out changes the accuracy by more than the tolerance; then "all" (realism) is.
    realism: bool = False
    # Depth-map sweeps name the pipeline's own setting here: then a setting is advised only if
    # the model's estimates from its maps beat the same model's estimate from an empty map
    # (points carry p_vs_no_contact), and the pipeline's own stays when none does; otherwise the
    # fastest setting would always be the one that throws the contact away.
    pipeline_setting: str = ""

    @property
    def informative(self) -> bool:
        """Whether only settings that beat the empty map may be advised."""
        return bool(self.pipeline_setting)

    def score(self, accuracy: float) -> float:
        """Accuracy turned into higher-is-better for the Pareto front."""
        return accuracy if self.higher_is_better else -accuracy


SPECS: dict[str, Spec] = {
    "density": Spec(
        "Point-cloud density",
        "How dense must the object cloud be for the estimate? (collected "
        "session: depth-maps made again from the recorded model poses; SSIM on the contact windows, "
        "where a sparse map's no-contact estimate cannot score)",
        "density",
        "depth-map CPU ms",
        "contact SSIM",
        True,
        0.01,
        (
            ("points_median", "model points"),
            ("thinning_ms", "thinning + index CPU ms (once per cloud)"),
            ("contact_ssim_se", "contact s.e."),
            PER_SESSION_EXTRA,
            ("p_vs_no_contact", "p vs empty map"),
            ("ssim", "whole-image SSIM"),
            ("paper_ssim", "paper SSIM"),
        ),
        pipeline_setting="unfiltered",
    ),
    "depth_map": Spec(
        "Depth-map rule: the surface against the nearest point",
        "What should a bin hold: the model's surface through it, or its nearest point (the paper's)? "
        "(collected session, depth-maps cut again by each rule from the recorded model poses and the "
        "default model trained on each; SSIM on the contact windows)",
        "rule",
        "CPU ms per depth-map",
        "contact SSIM",
        True,
        0.01,
        (
            ("contact_ssim_se", "contact s.e."),
            PER_SESSION_EXTRA,
            ("p_vs_no_contact", "p vs empty map"),
            ("dissimilarity_ratio", "dissimilarity ratio"),
            ("renderer_ratio", "renderer ratio"),
            ("training_s_per_epoch", "training CPU s/epoch"),
            ("ssim", "whole-image SSIM"),
        ),
        pipeline_setting="surface",
    ),
    "pose_sigma": Spec(
        "Pose uncertainty told to the model",
        "What in-plane pose error (pose_sigma_mm) should a planner pass with its depth-maps? (the "
        "session model serving the test split's maps with its physics prior blurred by each; SSIM "
        "on the contact windows)",
        "pose_sigma_mm",
        "CPU ms per region",
        "contact SSIM",
        True,
        # Every sigma costs the same blur: the most accurate is the advice, not the fastest
        # within a margin, which timing noise would choose.
        0.0,
        (
            ("contact_ssim_se", "contact s.e."),
            PER_SESSION_EXTRA,
            ("p_vs_no_contact", "p vs empty map"),
            ("dissimilarity_ratio", "dissimilarity ratio"),
            ("ssim", "whole-image SSIM"),
        ),
    ),
    "registration_voxel": Spec(
        "Registration voxel size",
        "Coarser FPFH voxels: faster, but how much pose error?",
        "voxel",
        "CPU ms per registration",
        "ADD-S median (mm)",
        False,
        0.5,
        REGISTRATION_EXTRAS,
    ),
    "registration_ransac": Spec(
        "RANSAC iterations",
        "How many sample-consensus iterations are worth it?",
        "iterations",
        "CPU ms per registration",
        "ADD-S median (mm)",
        False,
        0.5,
        REGISTRATION_EXTRAS,
    ),
    "registration_icp": Spec(
        "ICP distance stages",
        "Which ICP correspondence distances?",
        "stages",
        "CPU ms per registration",
        "ADD-S median (mm)",
        False,
        0.5,
        REGISTRATION_EXTRAS,
    ),
    "resolution": Spec(
        "Depth-map resolution",
        "Finer bins: do they pay for their training and inference time? "
        "(collected session, depth-maps made again at each size; SSIM at 100 x 100 on the contact "
        "windows)",
        "bins",
        "training CPU s/epoch",
        "contact SSIM",
        True,
        0.01,
        (
            ("inference_ms_per_region", "inference ms/region"),
            ("contact_ssim_se", "contact s.e."),
            PER_SESSION_EXTRA,
            ("p_vs_no_contact", "p vs empty map"),
            ("ssim", "whole-image SSIM"),
        ),
        pipeline_setting="100 x 100",
    ),
    "training_length": Spec(
        "Training length",
        "When does more training stop paying?",
        "epochs",
        "training CPU s",
        "validation SSIM",
        True,
        0.01,
        (("val_l1", "val L1"),),
    ),
    "depth_effects": Spec(
        "Simulated depth effects",
        "What does realistic depth data cost per frame, and what does registration lose on it?",
        "effects",
        "CPU ms per depth frame",
        "ADD-S median (mm)",
        False,
        0.5,
        (("registration_ms", "registration CPU ms"), ("accepted_rate", "accepted")),
        realism=True,
    ),
    "gelsight_effects": Spec(
        "Simulated GelSight effects",
        "What does a model trained without an effect lose "
        "when tested with it, and what does the effect cost per frame?",
        "effects on",
        "CPU ms per GelSight frame",
        "SSIM tested with them",
        True,
        0.01,
        (("ssim_lost", "SSIM lost"), ("ssim_se", "SSIM s.e.")),
        realism=True,
    ),
    "width": Spec(
        "Generator width (trained)",
        "Does a wider generator's network estimate better, for its time, and better than the physics "
        "prior alone (no network)?",
        "width",
        "CPU ms per region (eager fp32)",
        "SSIM",
        True,
        0.01,
        (("training_s_per_epoch", "training CPU s/epoch"), ("parameters", "parameters"), ("ssim_se", "SSIM s.e.")),
    ),
    "calibration_grasps": Spec(
        "Touch calibration of the depth cameras",
        "How many grasps must a session spend before its touches calibrate the cameras? (collected "
        "session, the first N training grasps; error against the scene's true extrinsics; beside it "
        "the test split's depth-maps cut with that calibration through the GelSight renderer; time at "
        "the session's own pace, and a simulated arm does not wait out its moves as a real one does)",
        "grasps",
        "session s + fit CPU s",
        "worse camera's error (mm)",
        False,
        0.1,
        (
            ("error_deg", "error deg"),
            ("touches", "touches"),
            ("touches_per_object", "touches per object"),
            ("renderer_ratio", "renderer ratio"),
            ("fit_cpu_s", "fit CPU s"),
            ("refused", "refused because"),
        ),
    ),
    "inference": Spec(
        "Generator width, precision, runtime",
        "Which variant serves the most regions per second without changing the estimate?",
        "variant",
        "ms per region (wall, batched, on the bench's threads)",
        "SSIM vs fp32 eager",
        True,
        0.01,
        (("regions_per_s", "regions/s"), ("p50_ms", "p50 ms (1 region)")),
    ),
    "uncertainty": Spec(
        "The uncertainty's method and cost",
        "Does the learned uncertainty a planner receives predict the served estimate's error better "
        "than the spread of dropout passes, and what does each add to the time? (collected session, "
        "the default model through the served path; r per pixel against |estimate - truth|, levels)",
        "method",
        "CPU ms per region",
        "r(u, error) per pixel",
        True,
        0.05,
        (
            ("region_r", "r(mean u, 1 - SSIM) per region"),
            ("decile_ratio_min", "RMS e / mean u, lowest decile ratio"),
            ("decile_ratio_max", "RMS e / mean u, highest decile ratio"),
            ("u_mean_levels", "mean u (levels)"),
            ("estimate_ms", "served estimate CPU ms/region"),
            ("refused", "refused because"),
        ),
    ),
    "serving": Spec(
        "What serves: the prior alone or the network, with or without the uncertainty",
        "What does each form a checkpoint could serve cost per region and score? (collected session, "
        "the default model through the served path from depth-maps, 64 regions a pass; SSIM on the "
        "contact windows; served: what the checkpoint serves)",
        "form",
        "CPU ms per region",
        "contact SSIM",
        True,
        0.01,
        (
            ("served", "served"),
            ("contact_ssim_se", "contact s.e."),
            PER_SESSION_EXTRA,
            ("p_vs_no_contact", "p vs empty map"),
            ("dissimilarity_ratio", "dissimilarity ratio"),
            ("regions_per_s", "regions per CPU s"),
            ("refused", "refused because"),
        ),
    ),
}
