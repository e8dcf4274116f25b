"""The simulator's effect registry: which effects a scene may call for, their parameters with
physical ranges and defaults, and the check of a scene's list against them.

Effects are named, composable pieces; :data:`EFFECTS` lists each one with its family
(``depth``, ``object``, ``arm``, ``gelsight``) and its parameters. A scene lists only the
effects it wants; an effect that is not listed is never run. The scene file lists them by name
(``workcell.scene``); :func:`resolve_effects` checks them here, where they are simulated, and
fills in the defaults. Every problem is a :class:`SceneError` naming the file and the key.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from sim.gelsight_effects import EFFECTS as GELSIGHT_EFFECT_CLASSES
from sim.gelsight_effects import make_effect
from workcell.scene import EffectSpec, Scene, SceneReader


@dataclasses.dataclass(frozen=True)
class Param:
    """One effect parameter: default, physical range [lo, hi] (None = unbounded), unit, and
    ``size`` (0 = scalar, n = list of n numbers, each in range)."""

    default: Any
    lo: float | None = None
    hi: float | None = None
    unit: str = ""
    size: int = 0
    choices: tuple = ()

    def describe(self) -> str:
        if self.choices:
            return f"one of {list(self.choices)}"
        rng = f"[{self.lo}, {self.hi}]" + (f" {self.unit}" if self.unit else "")
        return f"list of {self.size} numbers in {rng}" if self.size else f"number in {rng}"


@dataclasses.dataclass(frozen=True)
class EffectInfo:
    family: str
    params: dict[str, Param]
    doc: str
    per_camera: bool = False  # may carry a ``camera`` key restricting it to one camera


EFFECTS: dict[str, EffectInfo] = {
    # --- depth camera (Kinect v2); models and sources in sim/depth_effects.py ---
    "extrinsic_offset": EffectInfo(
        "depth",
        {
            "translation_mm": Param([0.0, 0.0, 0.0], -100.0, 100.0, "mm", size=3),
            "rotation_deg": Param([0.0, 0.0, 0.0], -10.0, 10.0, "deg", size=3),
        },
        "true camera pose = nominal pose * offset (camera frame); the driver reports the nominal",
        per_camera=True,
    ),
    "lateral_noise": EffectInfo(
        "depth",
        {"sigma_px": Param(0.5, 0.0, 5.0, "px")},
        "Gaussian jitter of each pixel's viewing ray (edges wander)",
        per_camera=True,
    ),
    "flying_pixels": EffectInfo(
        "depth",
        {"jump_m": Param(0.02, 0.002, 1.0, "m"), "probability": Param(0.5, 0.0, 1.0)},
        "mixed foreground/background returns at depth discontinuities",
        per_camera=True,
    ),
    "axial_noise": EffectInfo(
        "depth",
        {
            "a0_mm": Param(1.5, 0.0, 50.0, "mm"),
            "a1_mm_per_m": Param(-0.5, -50.0, 50.0, "mm/m"),
            "a2_mm_per_m2": Param(0.3, 0.0, 50.0, "mm/m^2"),
            "a3_mm": Param(0.1, 0.0, 50.0, "mm/m^1.5"),
            "scale": Param(1.0, 0.0, 10.0),
        },
        "Gaussian range noise sigma(z, theta) (Fankhauser et al. 2015)",
        per_camera=True,
    ),
    "missing_returns": EffectInfo(
        "depth",
        {
            "min_range_m": Param(0.5, 0.0, 2.0, "m"),
            "max_range_m": Param(4.5, 0.5, 10.0, "m"),
            "max_incidence_deg": Param(80.0, 30.0, 90.0, "deg"),
            "ramp_deg": Param(10.0, 0.0, 40.0, "deg"),
            "dropout_probability": Param(0.0, 0.0, 0.5),
        },
        "no return out of range, at grazing incidence, and at random",
        per_camera=True,
    ),
    "quantisation": EffectInfo(
        "depth", {"step_mm": Param(1.0, 0.01, 20.0, "mm")}, "depth rounded to the sensor's step", per_camera=True
    ),
    # --- objects ---
    "micro_relief": EffectInfo(
        "object",
        {"scale": Param(1.0, 0.0, 5.0)},
        "displaces object surfaces by the relief listed on each object (ridges, knurling, bumps)",
    ),
    # --- arm ---
    "arm_repeatability": EffectInfo(
        "arm",
        {"sigma_mm": Param(0.033, 0.0, 5.0, "mm"), "sigma_deg": Param(0.0, 0.0, 1.0, "deg")},
        "each move ends at the target plus Gaussian position (and orientation) error",
    ),
}

# Order in which depth effects run, whatever the order in the scene file: the geometric
# ones change what the rays hit, the measurement ones what the sensor reports.
DEPTH_EFFECT_ORDER = (
    "extrinsic_offset",
    "lateral_noise",
    "flying_pixels",
    "axial_noise",
    "missing_returns",
    "quantisation",
)


def _gelsight_effect_info(name: str, cls: type) -> EffectInfo:
    """A GelSight effect's registry entry, from its dataclass: the parameters' names and
    defaults; the ranges are the effect's own (checked by constructing it)."""
    params = {field.name: Param(field.default) for field in dataclasses.fields(cls)}
    return EffectInfo("gelsight", params, (cls.__doc__ or "").strip().splitlines()[0])


EFFECTS.update({name: _gelsight_effect_info(name, cls) for name, cls in GELSIGHT_EFFECT_CLASSES.items()})


def effects_of(scene: Scene, family: str) -> list[EffectSpec]:
    """The effects of ``family`` the scene calls for, in the scene's order."""
    return [spec for spec in scene.effects if EFFECTS[spec.name].family == family]


def resolve_effects(scene: Scene) -> Scene:
    """The scene with each effect checked against :data:`EFFECTS` and its defaults filled in
    (GelSight effects keep only the parameters written: the renderer has its own defaults).
    Resolving a resolved scene changes nothing."""
    reader = SceneReader(scene.path)
    return dataclasses.replace(scene, effects=[_resolve(reader, spec) for spec in scene.effects])


def _resolve(r: SceneReader, spec: EffectSpec) -> EffectSpec:
    key, name = spec.key, spec.name
    if name not in EFFECTS:
        r.fail(f"{key}.name", f"unknown effect {name!r}", sorted(EFFECTS))
    info = EFFECTS[name]
    allowed = set(info.params) | {"name"} | ({"camera"} if info.per_camera else set())
    if spec.camera is not None and not info.per_camera:
        r.fail(f"{key}.camera", f"unknown parameter of effect {name!r}", sorted(allowed))
    for k in spec.params:
        if k not in allowed:
            r.fail(f"{key}.{k}", f"unknown parameter of effect {name!r}", sorted(allowed))
    params: dict[str, Any] = {}
    for pname, p in info.params.items():
        if info.family == "gelsight" and pname not in spec.params:
            continue  # the renderer's own default
        v = spec.params.get(pname, p.default)
        pkey = f"{key}.{pname}"
        if p.choices:
            v = r.string(v, pkey, p.choices)
        elif p.size:
            v = r.vector(v, pkey, p.size, p.lo, p.hi, p.unit).tolist()
        elif p.lo is not None or p.hi is not None:
            v = r.number(v, pkey, p.lo, p.hi, p.unit)
        params[pname] = v
    if info.family == "gelsight":
        try:
            make_effect(name, params)
        except Exception as exc:  # noqa: BLE001 - GelSightRenderError or a bad type, reported with its key
            bad = next((k for k in params if k in str(exc)), None)
            r.fail(
                f"{key}.{bad}" if bad else key,
                f"invalid GelSight effect parameters: {exc}",
                {k: p.default for k, p in info.params.items()},
            )
    if name == "missing_returns" and params["max_range_m"] <= params["min_range_m"]:
        r.fail(f"{key}.max_range_m", "must exceed min_range_m", f"({params['min_range_m']}, 10.0] m")
    return dataclasses.replace(spec, params=params)
