"""Depth-camera effects of a Microsoft Kinect v2 (time-of-flight), each a separate piece.

Every effect is built only when the scene lists it, works on whole images at once (numpy,
no per-pixel Python) and draws its randomness from the ``numpy.random.Generator`` it is
given, so a fixed seed reproduces a frame exactly. The world's cameras (``sim/depth_render.py``)
run them in the fixed order of ``workcell.scene.DEPTH_EFFECT_ORDER``: the geometric ones first
(:class:`ExtrinsicOffset` moves the camera that casts the rays, :class:`LateralNoise`
jitters the rays), then the measurement ones on the z-depth image (metres, NaN = no return):
:class:`FlyingPixels`, :class:`AxialNoise`, :class:`MissingReturns`, :class:`Quantisation`.

Sources:
- Fankhauser, Bloesch, Rodriguez, Kaestner, Hutter, Siegwart, "Kinect v2 for Mobile Robot
  Navigation: Evaluation and Modeling", ICAR 2015: axial noise of the Kinect v2 as a function
  of range z (m) and incidence angle theta, fitted as
  ``sigma_z(z, theta) = a0 + a1 z + a2 z^2 + a3 z^1.5 theta^2 / (pi/2 - theta)^2`` (mm),
  reported as about 1.5 - 0.5 z + 0.3 z^2 + 0.1 z^1.5 theta^2/(pi/2-theta)^2 mm: a few mm
  at table range, growing toward grazing incidence. Those are our defaults; every
  coefficient is a scene parameter (the coefficients were set from the published model as
  we recall it and are not re-fitted here). Lateral noise there is of the order of a pixel,
  nearly independent of range.
- Nguyen, Izadi, Lovell, "Modeling Kinect Sensor Noise for Improved 3D Reconstruction and
  Tracking", 3DIMPVT 2012: the axial/lateral decomposition and the theta/(pi/2 - theta)
  growth toward grazing angles used above (Kinect v1).
- Sarbolandi, Lefloch, Kolb, "Kinect range sensing: Structured-light versus Time-of-Flight
  Kinect", CVIU 2015: ToF "flying pixels" (mixed foreground/background returns at depth
  discontinuities) and missing returns at grazing incidence / low signal.
- Lachat, Macher, Landes, Grussenmeyer, "Assessment and calibration of a RGB-D camera
  (Kinect v2 sensor) towards a potential use for close-range 3D modeling", Remote Sensing
  2015: working range 0.5-4.5 m, mm-level noise growing with range.
- Microsoft Kinect v2 specification: depth range 0.5-4.5 m, 512 x 424 depth image, depth
  delivered as 16-bit millimetres (hence the 1 mm quantisation).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation


def gaussian(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` standard normal float32 samples by the Box-Muller transform of float32 uniforms:
    about twice as fast as ``rng.standard_normal(n, dtype=float32)`` here (the draws of the
    noise effects dominate their cost); tails end near 5.8 sigma (float32 uniforms)."""
    half = (n + 1) // 2
    u = rng.random((2, half), dtype=np.float32)
    r = np.sqrt(np.float32(-2.0) * np.log1p(-u[0]))
    angle = np.float32(2.0 * math.pi) * u[1]
    out = np.empty(2 * half, dtype=np.float32)
    np.multiply(r, np.cos(angle), out=out[:half])
    np.multiply(r, np.sin(angle), out=out[half:])
    return out[:n]


class ExtrinsicOffset:
    """Camera extrinsic calibration error: the camera really sits at ``nominal @ offset``
    (offset given in the camera frame: translation in mm, rotation vector components in
    degrees); the driver keeps reporting the nominal pose. This is the systematic shift
    between point cloud and robot that the paper observed (§ data collection)."""

    name = "extrinsic_offset"

    def __init__(self, params: dict[str, Any]):
        self.translation_m = np.asarray(params["translation_mm"], float) * 1e-3
        self.rotation_rad = np.radians(np.asarray(params["rotation_deg"], float))

    def offset_matrix(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(self.rotation_rad).as_matrix()
        T[:3, 3] = self.translation_m
        return T


class LateralNoise:
    """Each pixel's viewing ray is jittered by Gaussian noise of ``sigma_px`` pixels in u and
    v before casting: depth edges wander sideways by about a pixel (Fankhauser et al. 2015
    report lateral noise of this order for the Kinect v2)."""

    name = "lateral_noise"

    def __init__(self, params: dict[str, Any]):
        self.sigma_px = float(params["sigma_px"])

    def jitter(self, u: np.ndarray, v: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        du = gaussian(rng, u.size).reshape(u.shape) * np.float32(self.sigma_px)
        dv = gaussian(rng, v.size).reshape(v.shape) * np.float32(self.sigma_px)
        return u + du, v + dv


def _neighbours(z: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """4 x len(idx) depths of the up/down/left/right neighbours of flat indices ``idx``
    (NaN outside the image)."""
    h, w = z.shape
    r, c = np.divmod(idx, w)
    zf = z.reshape(-1)
    out = np.full((4, idx.size), np.nan, dtype=z.dtype)
    for k, (dr, dc) in enumerate(((-1, 0), (1, 0), (0, -1), (0, 1))):
        rr, cc = r + dr, c + dc
        ok = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
        out[k, ok] = zf[rr[ok] * w + cc[ok]]
    return out


class FlyingPixels:
    """At a depth discontinuity larger than ``jump_m`` a time-of-flight pixel integrates light
    from both surfaces and reports a depth in between (Sarbolandi et al. 2015). Each pixel on
    either side of such a jump (4-neighbourhood) becomes, with ``probability``,
    ``z + a (z_other - z)`` with ``a ~ U(0, 1)`` and ``z_other`` the neighbour across the
    larger jump. Edges against "no return" are left alone (nothing to mix with)."""

    name = "flying_pixels"

    def __init__(self, params: dict[str, Any]):
        self.jump_m = float(params["jump_m"])
        self.probability = float(params["probability"])

    def apply(self, z: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        jump = np.float32(self.jump_m)
        with np.errstate(invalid="ignore"):
            eh = np.abs(z[:, 1:] - z[:, :-1]) > jump  # NaN compares False
            ev = np.abs(z[1:, :] - z[:-1, :]) > jump
        edge = np.zeros(z.shape, dtype=bool)
        edge[:, 1:] |= eh
        edge[:, :-1] |= eh
        edge[1:, :] |= ev
        edge[:-1, :] |= ev
        idx = np.flatnonzero(edge)
        if idx.size == 0:
            return z
        pick = rng.random(idx.size) < self.probability
        alpha = rng.random(idx.size).astype(np.float32)
        idx, alpha = idx[pick], alpha[pick]
        neigh = _neighbours(z, idx)
        hi = np.fmax.reduce(neigh, axis=0)
        lo = np.fmin.reduce(neigh, axis=0)
        zc = z.reshape(-1)[idx]
        other = np.where(np.nan_to_num(hi - zc, nan=-1.0) >= np.nan_to_num(zc - lo, nan=-1.0), hi, lo)
        out = z.copy()
        out.reshape(-1)[idx] = zc + alpha * (other - zc)
        return out


class AxialNoise:
    """Gaussian noise along the viewing ray with the Kinect v2 model of Fankhauser et al.
    (2015): ``sigma_z = scale (a0 + a1 z + a2 z^2 + a3 z^1.5 theta^2/(pi/2 - theta)^2)`` mm,
    z in m, theta the incidence angle between the ray and the surface normal."""

    name = "axial_noise"

    def __init__(self, params: dict[str, Any]):
        self.a0, self.a1, self.a2, self.a3 = (
            float(params[k]) for k in ("a0_mm", "a1_mm_per_m", "a2_mm_per_m2", "a3_mm")
        )
        self.scale = float(params["scale"])

    def sigma_m(self, z: np.ndarray, cos_incidence: np.ndarray) -> np.ndarray:
        theta = np.arccos(np.clip(cos_incidence, 0.0, 1.0))
        theta = np.minimum(theta, np.float32(math.pi / 2 - 1e-2))
        ratio = theta / (np.float32(math.pi / 2) - theta)
        sigma_mm = self.a0 + self.a1 * z + self.a2 * z * z + self.a3 * z * np.sqrt(z) * ratio * ratio
        return np.maximum(sigma_mm, 0.0) * (1e-3 * self.scale)

    def apply(
        self,
        z: np.ndarray,
        cos_incidence: np.ndarray,
        rng: np.random.Generator,
        sigma_static: np.ndarray | None = None,
        dynamic_idx: np.ndarray | None = None,
    ) -> np.ndarray:
        """``sigma_static`` (optional, HxW): sigma already evaluated on the exact geometry
        (range and incidence are properties of the true surface); pixels in ``dynamic_idx``
        (re-cast this frame) and pixels without a static value are evaluated here."""
        idx = np.flatnonzero(np.isfinite(z))
        out = z.copy()
        zf = z.reshape(-1)[idx]
        if sigma_static is None:
            sigma = self.sigma_m(zf, cos_incidence.reshape(-1)[idx])
        else:
            full = sigma_static.reshape(-1)
            if dynamic_idx is not None and dynamic_idx.size:
                full = full.copy()
                full[dynamic_idx] = self.sigma_m(z.reshape(-1)[dynamic_idx], cos_incidence.reshape(-1)[dynamic_idx])
            sigma = full[idx]
            missing = np.isnan(sigma)
            if missing.any():
                sigma[missing] = self.sigma_m(zf[missing], cos_incidence.reshape(-1)[idx[missing]])
        out.reshape(-1)[idx] = zf + sigma.astype(np.float32) * gaussian(rng, idx.size)
        return out


class MissingReturns:
    """Pixels without a return: range outside [min_range_m, max_range_m] (Kinect v2: 0.5 to
    4.5 m), incidence beyond ``max_incidence_deg`` (with the drop probability rising linearly
    over the last ``ramp_deg``), plus a uniform ``dropout_probability``."""

    name = "missing_returns"

    def __init__(self, params: dict[str, Any]):
        self.min_range = float(params["min_range_m"])
        self.max_range = float(params["max_range_m"])
        self.max_inc = math.radians(float(params["max_incidence_deg"]))
        self.ramp = math.radians(float(params["ramp_deg"]))
        self.dropout = float(params["dropout_probability"])

    def apply(self, z: np.ndarray, cos_incidence: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        out = z.copy()
        with np.errstate(invalid="ignore"):
            drop = (z < self.min_range) | (z > self.max_range)
            cos_max = math.cos(self.max_inc)
            drop |= cos_incidence < cos_max
            if self.ramp > 0:
                cos_start = math.cos(max(self.max_inc - self.ramp, 0.0))
                ramp = np.isfinite(z) & (cos_incidence < cos_start) & (cos_incidence >= cos_max)
                idx = np.flatnonzero(ramp)
                if idx.size:
                    theta = np.arccos(np.clip(cos_incidence.reshape(-1)[idx], 0.0, 1.0))
                    p = (theta - (self.max_inc - self.ramp)) / self.ramp
                    drop.reshape(-1)[idx[rng.random(idx.size) < p]] = True
        if self.dropout > 0:
            drop |= rng.random(z.shape) < self.dropout
        out[drop] = np.nan
        return out


class Quantisation:
    """Depth rounded to ``step_mm`` (the Kinect v2 delivers 16-bit millimetres)."""

    name = "quantisation"

    def __init__(self, params: dict[str, Any]):
        self.step_m = np.float32(float(params["step_mm"]) * 1e-3)

    def apply(self, z: np.ndarray) -> np.ndarray:
        return (np.round(z / self.step_m) * self.step_m).astype(np.float32)


DEPTH_EFFECT_CLASSES = {
    cls.name: cls for cls in (ExtrinsicOffset, LateralNoise, FlyingPixels, AxialNoise, MissingReturns, Quantisation)
}


def _incidence(cos_incidence: np.ndarray | None, effect: str) -> np.ndarray:
    """The cosine of each pixel's incidence angle, which ``effect`` reads: a caller of a chain
    that :attr:`DepthEffectChain.needs_incidence` passes it."""
    if cos_incidence is None:
        raise ValueError(f"the {effect} depth effect needs each pixel's cos incidence, and none was given")
    return cos_incidence


class DepthEffectChain:
    """The depth effects one camera runs, built from the scene's effect list (only those
    listed; none listed = ideal, exact depth)."""

    def __init__(self, specs: list):
        self.by_name: dict[str, Any] = {}
        for spec in specs:
            self.by_name[spec.name] = DEPTH_EFFECT_CLASSES[spec.name](spec.params)
        self.extrinsic: ExtrinsicOffset | None = self.by_name.get("extrinsic_offset")
        self.lateral: LateralNoise | None = self.by_name.get("lateral_noise")
        self.flying: FlyingPixels | None = self.by_name.get("flying_pixels")
        self.axial: AxialNoise | None = self.by_name.get("axial_noise")
        self.missing: MissingReturns | None = self.by_name.get("missing_returns")
        self.quantise: Quantisation | None = self.by_name.get("quantisation")

    @property
    def needs_incidence(self) -> bool:
        return self.axial is not None or self.missing is not None

    def prepare(self, z: np.ndarray, cos_incidence: np.ndarray | None) -> dict:
        """Per-pixel quantities of the exact (static) image the effects can reuse each frame."""
        static: dict = {}
        if self.axial is not None:
            with np.errstate(invalid="ignore"):
                sigma = self.axial.sigma_m(z, _incidence(cos_incidence, self.axial.name))
                static["axial_sigma"] = sigma.astype(np.float32)
        return static

    def measure(
        self,
        z: np.ndarray,
        cos_incidence: np.ndarray | None,
        rng: np.random.Generator,
        static: dict | None = None,
        dynamic_idx: np.ndarray | None = None,
    ) -> np.ndarray:
        """Run the measurement effects on the z-depth image, in the order of
        ``workcell.scene.DEPTH_EFFECT_ORDER``. ``static`` comes from :meth:`prepare` on the exact
        image; ``dynamic_idx`` are the pixels whose ray changed this frame."""
        static = static or {}
        if self.flying is not None:
            z = self.flying.apply(z, rng)
        if self.axial is not None:
            cos_axial = _incidence(cos_incidence, self.axial.name)
            z = self.axial.apply(z, cos_axial, rng, static.get("axial_sigma"), dynamic_idx)
        if self.missing is not None:
            z = self.missing.apply(z, _incidence(cos_incidence, self.missing.name), rng)
        if self.quantise is not None:
            z = self.quantise.apply(z)
        return z
