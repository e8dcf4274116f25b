"""The project's own setting in each of the report's tables, read from the code that sets it, so
that the report says whether its recommendation is the default a lab gets, and why not where it
is not.

A table's rows are labelled by the sweeps (report.sweeps); each entry here names, in the same
words, the row the pipeline runs by default. A row flagged by its sweep (``served``: what the
checkpoint serves; ``model_default``: the model's own value) is that sweep's default."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from models.checkpoint import TrainConfig

# The settings' owners load only when a report is written: `dtx` itself starts without torch
# or Open3D, and report.cli imports this module through report.write.
# ruff: noqa: PLC0415

Points = Sequence[dict[str, Any]]
REPO = Path(__file__).resolve().parent.parent

# The scene the report's registration and effects sweeps run on, and make demo collects in.
DEFAULT_SCENE = "scenes/ycb_three.yaml"


def _default_config() -> TrainConfig:
    from models.checkpoint import TrainConfig

    return TrainConfig.load(REPO / "configs" / "quick.yaml")


def _effects_label(names: Sequence[str], every: Sequence[str]) -> str:
    """The effects sweeps' row label of a set of effects (report.sweeps)."""
    if not names:
        return "none"
    return "all" if set(names) >= set(every) and len(names) > 1 else names[0]


def _scene_effects(every: Sequence[str]) -> str:
    """What the default scene calls for among ``every`` effect of a kind."""
    from workcell.scene import load_scene

    listed = sorted({spec.name for spec in load_scene(REPO / DEFAULT_SCENE).effects} & set(every))
    return _effects_label(listed, every)


def _flagged(flag: str) -> Callable[[Points], str | None]:
    def label(points: Points) -> str | None:
        return next((p["setting"] for p in points if p.get(flag)), None)

    return label


def _most_grasps(points: Points) -> str | None:
    """``dtx calibrate touches`` uses every grasp of the session unless told --grasps."""
    counted = [p for p in points if p["setting"].endswith(" grasps")]
    return max(counted, key=lambda p: int(p["setting"].split()[0]))["setting"] if counted else None


def _constant(value: Callable[[], str]) -> Callable[[Points], str | None]:
    return lambda points: value()


def _registration(field: str) -> Any:
    from perception.registration import RegistrationParams

    return getattr(RegistrationParams(), field)


def _depth_map(field: str) -> Any:
    from perception.depthmap import DepthMapParams

    return getattr(DepthMapParams(), field)


def _gelsight_effects() -> str:
    from sim.gelsight_effects import EFFECTS

    return _scene_effects(list(EFFECTS))


def _inference() -> str:
    from nodes.inference import InferenceNode

    params = InferenceNode.Params()
    return f"width {_default_config().generator.ngf} {params.precision} {params.runtime}"


PROJECT_DEFAULTS: dict[str, Callable[[Points], str | None]] = {
    "density": _constant(lambda: "unfiltered"),
    "registration_voxel": _constant(lambda: f"{_registration('voxel_size_m') * 1e3:g} mm"),
    "registration_ransac": _constant(lambda: f"{_registration('ransac_max_iterations'):,}"),
    "registration_icp": _constant(lambda: "/".join(f"{d * 1e3:g}" for d in _registration("icp_distances_m")) + " mm"),
    "resolution": _constant(lambda: "{} x {}".format(*_depth_map("shape"))),
    "training_length": _constant(lambda: f"{_default_config().epochs + _default_config().epochs_decay} epoch(s)"),
    "depth_effects": _constant(lambda: "all"),
    "gelsight_effects": _constant(_gelsight_effects),
    "width": _constant(lambda: f"width {_default_config().generator.ngf}"),
    "inference": _constant(_inference),
    "calibration_grasps": _most_grasps,
    "depth_map": _constant(lambda: _depth_map("method")),
    "pose_sigma": _flagged("model_default"),
    "uncertainty": _constant(lambda: "learned (served)"),
    "serving": _flagged("served"),
}

# Where the project keeps a default the report does not recommend, why: a judgement the
# measurement alone cannot make.
WHY_NOT: dict[str, str] = {
    "density": (
        "the patch extractor cuts from each object's whole model cloud, indexed once per session, and "
        "its cut runs beside the GelSight capture (What each second buys), so a thinner cloud saves a "
        "grasp no time; thinning is for a planner's own clouds, and this table says what it costs them"
    ),
    "depth_map": (
        "the nearest point is as good only on clouds as dense as the pipeline's own: thinned to 10,000 "
        "points/cm³ its estimate fell below the empty map's on make demo's contact windows (0.739 "
        "against 0.833) where the surface keeps 0.908, and on unseen objects its ratio was 0.47 "
        "against 0.4501 (docs/measurements.md, issue 50)"
    ),
    "resolution": (
        "the model's image is the tactile image's size (100 x 100, the paper's); a coarser map answers at "
        "a fraction of the tactile image's resolution, which scores within the table's tolerance here, "
        "where what is left of the registration's pose error blurs every simulated contact, and is not "
        "measured on a real press's sharp one"
    ),
    "training_length": (
        "this table trains on the analytic contacts alone; the default trains a session beside a "
        "contact library in 3 + 3 epochs, as many steps as 5 + 5 of the session alone, chosen on make "
        "demo's data (configs/quick.yaml)"
    ),
    "registration_voxel": (
        "registration runs once an object a session (the median grasp reuses its pose: What each second "
        "buys), so the CPU a coarser voxel saves is not a grasp's time; with the touch-calibrated cameras "
        "(the calibrated columns) the coarsest voxel is the one that loses accuracy; the default keeps the "
        "margin chosen on thin and flat objects, which this table does not hold"
    ),
    "registration_ransac": (
        "the settings' times differ by less than repeated runs of one do, and registration runs once "
        "an object a session; the default keeps the margin chosen for harder scenes"
    ),
    "registration_icp": (
        "a single stage needs the coarse pose already within its distance (with touch-calibrated cameras "
        "the p90 column shows the poses a short one misses); the two stages recover a coarse pose further "
        "off, and registration runs once an object a session"
    ),
    "width": (
        "a checkpoint serves its prior alone wherever its network does not lead it on validation "
        "(models.serving.choose_served; the serving table: the default model serves its prior); the "
        "width-16 network is trained beside it, to serve where it measurably helps (a lab's real frames, "
        "a scene with effects the prior lacks)"
    ),
    "inference": (
        "the default checkpoint serves its prior alone and runs no network (the serving table); for one "
        "that serves its network, fp32 ONNX Runtime changes no pixel and answers a single region, a "
        "planner's quickest call, fastest or nearly (the p50 column), on any x86 CPU, where bf16 and "
        "int8 are fast only on CPUs with their instructions (bf16: AVX-512 BF16 or AMX; int8: VNNI); a "
        "lab serving a network on such a CPU passes precision:= and runtime:= to launch/serve.yaml"
    ),
    "serving": (
        "the uncertainty is what a planner weighs each estimate by (the uncertainty table: its r with "
        "the error against dropout's), which SSIM cannot value; it is served with every estimate"
    ),
    "calibration_grasps": (
        "touches cost no robot time of their own (each grasp of a session makes two), only the fit's "
        "CPU; a lab calibrates from every grasp it collected"
    ),
    "gelsight_effects": (
        "a scene simulates only the GelSight effects it calls for (scenes/*.yaml `effects`): the default "
        "scene's sensor is noisy but has no markers and a steady light; a lab whose sensor shows them "
        "lists them in its scene, and this table says what a model trained without them loses"
    ),
    "depth_effects": (
        "the default scene calls for every depth effect a Kinect v2 shows; leaving one out would make "
        "the registration figures ones a real camera does not reach"
    ),
}


def project_default(sweep: str, points: Points) -> str | None:
    """The row label of the project's default among ``points`` of ``sweep`` (None: no entry, or
    the sweep flags none)."""
    label = PROJECT_DEFAULTS.get(sweep)
    return None if label is None else label(points)


def default_line(sweep: str, points: Points) -> str:
    """'Project default: ...': the default's row, whether it is the recommended one, and if not why."""
    default = project_default(sweep, points)
    chosen = next((p["setting"] for p in points if p.get("recommended")), None)
    if default is None:
        return "Project default: none named for this table."
    measured = "" if any(p["setting"] == default for p in points) else " (not among the settings measured here)"
    if default == chosen:
        return f"Project default: **{default}**, the recommended."
    why = WHY_NOT.get(sweep)
    if why is not None:
        return f"Project default: **{default}**{measured}, not the recommended: {why}."
    return (
        f"Project default: **{default}**{measured}, not the recommended **{chosen}**: no reason is recorded "
        "(report/defaults.py WHY_NOT); measure it with the full form before changing the default."
    )
