"""SimWorld depth rendering: exact geometry without effects, each effect alone changes only
what it models, determinism with a seed."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.seeding import state_rng
from sim.world import SimWorld
from workcell.scene import parse_scene

TOP_H = 1.0  # top-down camera height above the table (m)


def scene_dict(objects=None, effects=None, oblique=True) -> dict:
    cams = [{"name": "top", "pose": {"position_m": [0.0, 0.0, TOP_H], "look_at_m": [0.0, 0.0, 0.0]}}]
    if oblique:
        cams.append({"name": "side", "pose": {"position_m": [0.1, -1.0, 0.75], "look_at_m": [0.0, 0.0, 0.05]}})
    return {
        "name": "test",
        "workspace": {"min_m": [-0.35, -0.3, 0.0], "max_m": [0.35, 0.3, 0.5]},
        "table": {"size_m": [3.0, 3.0], "thickness_m": 0.03},
        "objects": objects if objects is not None else [],
        "cameras": cams,
        "effects": effects or [],
    }


def world(objects=None, effects=None, seed=0, oblique=True) -> SimWorld:
    return SimWorld(parse_scene(scene_dict(objects, effects, oblique)), seed=seed)


SPHERE = [{"name": "ball", "primitive": {"sphere": 0.1}, "pose": {"x_m": 0.0, "y_m": 0.0}}]
BOX = [{"name": "box", "primitive": {"box": [0.06, 0.08, 0.10]}, "pose": {"x_m": 0.05, "y_m": 0.0, "yaw_deg": 20}}]


def plane_depth(w: SimWorld, cam: str) -> np.ndarray:
    """Analytic z-depth of the table plane z = 0 (float64)."""
    c = w.cameras[cam]
    T = c.true_to_world
    d = c.dirs_cam.astype(np.float64) @ T[:3, :3].T
    t = -T[2, 3] / d[:, 2]
    t[t <= 0] = np.nan
    return t.reshape(c.spec.height, c.spec.width)


def test_plane_exact_top_down() -> None:
    w = world(oblique=False)
    z = w.render_depth("top")
    assert z.dtype == np.float32 and z.shape == (424, 512)
    assert np.all(np.isfinite(z))
    assert np.max(np.abs(z - TOP_H)) < 2e-6  # float32 precision at 1 m


def test_plane_exact_oblique() -> None:
    w = world()
    z = w.render_depth("side")
    ref = plane_depth(w, "side")
    hit = np.isfinite(z)
    assert hit.mean() > 0.3
    rel = np.abs(z[hit] - ref[hit]) / ref[hit]
    assert rel.max() < 2e-6


def test_sphere_exact() -> None:
    """Sphere hits are moved onto the analytic sphere: float precision wherever the ray hits
    (the tessellation only decides which pixels at the very silhouette see the sphere)."""
    w = world(SPHERE, oblique=False)
    z = w.render_depth("top").astype(np.float64)
    c = w.cameras["top"]
    rays = c.rays.numpy().astype(np.float64)  # the float32 rays actually cast
    o, d = rays[:, :3], rays[:, 3:]
    centre = np.array([0.0, 0.0, 0.1])
    oc = o - centre
    a = np.einsum("ij,ij->i", d, d)
    b = np.einsum("ij,ij->i", oc, d)
    cc = np.einsum("ij,ij->i", oc, oc) - 0.1**2
    disc = b * b - a * cc
    t = np.where(disc > 0, (-b - np.sqrt(np.clip(disc, 0, None))) / a, np.nan).reshape(z.shape)
    on_sphere = np.isfinite(t) & (np.abs(z - TOP_H) > 1e-3)
    assert on_sphere.sum() > 5000
    rel = np.abs(z[on_sphere] - t[on_sphere]) / t[on_sphere]
    assert rel.max() < 1e-6
    # pixels the analytic sphere covers but the render does not: only at the silhouette
    missed = np.isfinite(t) & ~on_sphere
    assert missed.sum() < 0.01 * np.isfinite(t).sum()
    # elsewhere the table at TOP_H
    table = np.isnan(t) & np.isfinite(z)
    assert np.max(np.abs(z[table] - TOP_H)) < 2e-6


def test_no_effects_cost_nothing() -> None:
    w = world(BOX)
    for cam in w.cameras.values():
        assert cam.effects.by_name == {}
    assert w.relief_scale == 0.0
    a, b = w.render_depth("side"), w.render_depth("side")
    np.testing.assert_array_equal(a, b)


# ------------------------------------------------------------------ effect isolation


def _pair(effect: dict, objects=BOX, seed=0):
    ideal = world(objects, seed=seed).render_depth("side")
    noisy = world(objects, [effect], seed=seed).render_depth("side")
    return ideal, noisy


def test_axial_noise_only_perturbs_depth_with_model_sigma() -> None:
    ideal, noisy = _pair({"name": "axial_noise"})
    np.testing.assert_array_equal(np.isnan(ideal), np.isnan(noisy))
    diff = (noisy - ideal)[np.isfinite(ideal)].astype(np.float64)
    assert abs(diff.mean()) < 2e-4
    # Fankhauser et al. model at ~1.2 m, moderate incidence: ~1.5 mm
    assert 0.8e-3 < diff.std() < 4e-3


def test_lateral_noise_moves_edges_only() -> None:
    w0 = world(BOX, oblique=False)
    w1 = world(BOX, [{"name": "lateral_noise", "sigma_px": 0.5}], oblique=False)
    ideal, noisy = w0.render_depth("top"), w1.render_depth("top")
    changed = ~((ideal == noisy) | (np.isnan(ideal) & np.isnan(noisy)))
    cast = w1.cameras["top"].cache
    assert cast is not None and cast.lateral is not None
    near_edge = cast.lateral.recast_idx
    mask = np.zeros(ideal.size, bool)
    mask[near_edge] = True
    mask = mask.reshape(ideal.shape)
    big = changed & (np.abs(np.nan_to_num(noisy - ideal, nan=1.0)) > 1e-5)
    assert big.any()
    assert not np.any(big & ~mask)  # large changes only next to depth discontinuities
    interior = np.isfinite(ideal) & ~mask
    np.testing.assert_allclose(noisy[interior], ideal[interior], rtol=2e-6)


def test_lateral_noise_on_a_tilted_plane_is_subpixel() -> None:
    ideal, noisy = _pair({"name": "lateral_noise", "sigma_px": 0.5}, objects=[])
    from scipy import ndimage

    both = ndimage.binary_erosion(np.isfinite(ideal), iterations=3) & np.isfinite(noisy)
    gy, gx = np.gradient(ideal.astype(np.float64))
    slope = np.hypot(np.nan_to_num(gx), np.nan_to_num(gy))
    bound = 1.5 * np.sqrt(2) * slope + 1e-6  # jitter truncated at 3 sigma = 1.5 px
    assert np.all(np.abs(noisy - ideal)[both] <= bound[both] * 1.05 + 1e-5)


def test_flying_pixels_only_at_discontinuities() -> None:
    ideal, noisy = _pair({"name": "flying_pixels", "jump_m": 0.02, "probability": 1.0})
    np.testing.assert_array_equal(np.isnan(ideal), np.isnan(noisy))
    changed = np.isfinite(ideal) & (noisy != ideal)
    assert changed.sum() > 50
    pad = np.pad(ideal, 1, constant_values=np.nan)
    neigh = np.stack([pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]])
    hi, lo = np.fmax.reduce(neigh, axis=0), np.fmin.reduce(neigh, axis=0)
    jump = np.fmax(hi - ideal, ideal - lo) > 0.02
    assert not np.any(changed & ~jump)
    assert np.all((noisy[changed] >= lo[changed] - 1e-6) & (noisy[changed] <= hi[changed] + 1e-6))


def test_missing_returns_only_drop_pixels() -> None:
    ideal, noisy = _pair(
        {"name": "missing_returns", "max_incidence_deg": 60.0, "ramp_deg": 0.0, "min_range_m": 0.5, "max_range_m": 1.2}
    )
    kept = np.isfinite(noisy)
    np.testing.assert_array_equal(noisy[kept], ideal[kept])
    assert np.all(np.isnan(noisy[np.isnan(ideal)]))
    dropped = np.isfinite(ideal) & ~kept
    assert dropped.sum() > 100
    assert np.all(ideal[kept] <= 1.2)


def test_missing_returns_out_of_range() -> None:
    w = world(oblique=False, effects=[{"name": "missing_returns", "max_range_m": 0.9}])
    assert np.all(np.isnan(w.render_depth("top")))  # table at 1.0 m, beyond 0.9 m


def test_quantisation_only_rounds() -> None:
    ideal, noisy = _pair({"name": "quantisation", "step_mm": 1.0})
    np.testing.assert_array_equal(np.isnan(ideal), np.isnan(noisy))
    f = np.isfinite(ideal)
    assert np.max(np.abs(noisy[f] - ideal[f])) <= 0.5e-3 + 1e-6
    mm = noisy[f] * 1000.0
    assert np.max(np.abs(mm - np.round(mm))) < 1e-3


def test_extrinsic_offset_is_a_moved_camera() -> None:
    eff = {
        "name": "extrinsic_offset",
        "camera": "side",
        "translation_mm": [5.0, -3.0, 4.0],
        "rotation_deg": [0.3, -0.2, 0.1],
    }
    w = world(BOX, [eff])
    offset = w.cameras["side"]
    assert not np.allclose(offset.true_to_world, offset.nominal_to_world)
    np.testing.assert_allclose(offset.nominal_to_world, w.scene.camera("side").camera_to_world)
    # the same image as an ideal camera placed at the true pose
    scene = parse_scene(scene_dict(BOX))
    scene.cameras[1].camera_to_world = offset.true_to_world.copy()
    ref = SimWorld(scene).render_depth("side")
    np.testing.assert_array_equal(w.render_depth("side"), ref)
    # the other camera is untouched
    np.testing.assert_array_equal(w.render_depth("top"), world(BOX).render_depth("top"))
    delta = np.linalg.inv(offset.nominal_to_world) @ offset.true_to_world
    np.testing.assert_allclose(delta[:3, 3], [0.005, -0.003, 0.004], atol=1e-9)


def test_micro_relief_only_on_relief_objects() -> None:
    objs = [
        {
            "name": "box",
            "primitive": {"box": [0.06, 0.08, 0.10]},
            "pose": {"x_m": 0.0, "y_m": 0.0},
            "relief": [{"kind": "ridges", "pitch_mm": 2.0, "depth_mm": 0.5, "axis": [0, 0, 1]}],
        },
        {"name": "plain", "primitive": {"box": [0.05, 0.05, 0.05]}, "pose": {"x_m": 0.2, "y_m": 0.1}},
    ]
    ideal = world(objs).render_depth("side")
    w = world(objs, [{"name": "micro_relief"}])
    relief = w.render_depth("side")
    np.testing.assert_array_equal(np.isnan(ideal), np.isnan(relief))
    diff = np.nan_to_num(ideal - relief)
    assert diff.min() >= -1e-7  # relief only raises surfaces toward the camera
    assert diff.max() > 2e-4
    # pixels not on the relief object are unchanged
    c = w.cameras["side"]
    ans = w.depth.raycast_scene.cast_rays(c.rays)
    gid = ans["geometry_ids"].numpy().reshape(ideal.shape)
    relief_gid = [g for g, oi in w.depth.geom_to_object.items() if oi == 0][0]
    other = gid != relief_gid
    np.testing.assert_array_equal(ideal[other], relief[other])


def test_relief_listed_but_not_called_for_is_ideal() -> None:
    objs = [
        {
            "name": "box",
            "primitive": {"box": [0.06, 0.08, 0.10]},
            "pose": {"x_m": 0.0, "y_m": 0.0},
            "relief": [{"kind": "bumps", "pitch_mm": 2.0, "depth_mm": 0.5}],
        }
    ]
    plain = [{"name": "box", "primitive": {"box": [0.06, 0.08, 0.10]}, "pose": {"x_m": 0.0, "y_m": 0.0}}]
    np.testing.assert_array_equal(world(objs).render_depth("side"), world(plain).render_depth("side"))


# ------------------------------------------------------------------ determinism

ALL = [
    {"name": "lateral_noise"},
    {"name": "flying_pixels"},
    {"name": "axial_noise"},
    {"name": "missing_returns", "dropout_probability": 0.05},
    {"name": "quantisation"},
]


def test_fixed_seed_reproduces_frames() -> None:
    a, b = world(BOX, ALL, seed=3), world(BOX, ALL, seed=3)
    for _ in range(2):
        np.testing.assert_array_equal(a.render_depth("side"), b.render_depth("side"))
    c = world(BOX, ALL, seed=4)
    assert not np.array_equal(a.render_depth("side"), c.render_depth("side"), equal_nan=True)
    # the static world's frames carry the noise of the state they show: whichever frame a node
    # takes, it sees the same one (sim.seeding); a fresh generator still draws fresh noise
    np.testing.assert_array_equal(a.render_depth("side"), a.render_depth("side"))
    assert not np.array_equal(
        a.render_depth("side"), a.render_depth("side", rng=np.random.default_rng(1)), equal_nan=True
    )


def test_explicit_rng() -> None:
    w = world(BOX, ALL)
    f1 = w.render_depth("side", rng=np.random.default_rng(9))
    f2 = w.render_depth("side", rng=np.random.default_rng(9))
    np.testing.assert_array_equal(f1, f2)


def test_point_cloud_uses_nominal_extrinsic() -> None:
    w = world([], [{"name": "extrinsic_offset", "camera": "side", "translation_mm": [0.0, 0.0, 20.0]}])
    pts_nominal = w.point_cloud("side")
    pts_true = w.point_cloud("side", nominal=False)
    assert np.max(np.abs(pts_true[:, 2])) < 1e-5  # the true pose puts the table at z = 0
    assert abs(np.median(pts_nominal[:, 2]) - np.median(pts_true[:, 2])) > 1e-3


@pytest.mark.parametrize("name", ["ycb_three", "ideal"])
def test_shipped_scene_frames(name: str) -> None:
    from workcell.scene import load_scene

    w = SimWorld(load_scene(f"scenes/{name}.yaml"))
    for cam in w.camera_names():
        z = w.render_depth(cam)
        f = z[np.isfinite(z)]
        assert f.size > 10000 and 0.5 < f.min() and f.max() < 4.5


@given(st.binary(max_size=64), st.binary(max_size=64), st.integers(0, 2**32 - 1), st.integers(0, 99))
@settings(max_examples=50, deadline=None)
def test_a_keyed_draw_depends_on_its_state_and_nothing_else(state: bytes, other: bytes, seed: int, stream: int) -> None:
    draws = state_rng(state, seed, stream).integers(0, 2**62, 4)
    np.testing.assert_array_equal(draws, state_rng(state, seed, stream).integers(0, 2**62, 4))
    if other != state:
        assert not np.array_equal(draws, state_rng(other, seed, stream).integers(0, 2**62, 4))
    assert not np.array_equal(draws, state_rng(state, seed, stream + 1).integers(0, 2**62, 4))
