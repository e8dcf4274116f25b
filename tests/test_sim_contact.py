"""Grasp contact: the gels close onto a box and a cylinder, press in as the gel's compliance
and the force say, and give gap maps at the GelSight size and at 100 x 100."""

from __future__ import annotations

import numpy as np
import pytest

from perception.depthmap import DepthMapParams, contact_depth_map, crop_bounds
from perception.gripper_centring import centre_between_gels
from sim.world import SimWorld
from workcell.kinematics import gel_poses_world, grasp_to_tcp_pose
from workcell.scene import parse_scene

K = 0.25 / 2.0  # default gel: E = 0.25 MPa over 2 mm -> 0.125 N/mm per mm^2
GEL = (18.6, 24.9)  # mm


def make_world(obj: dict, effects=None) -> SimWorld:
    return SimWorld(
        parse_scene(
            {
                "workspace": {"min_m": [-0.35, -0.3, 0.0], "max_m": [0.35, 0.3, 0.5]},
                "objects": [obj],
                "cameras": [{"name": "top", "pose": {"position_m": [0, 0, 1.0], "look_at_m": [0, 0, 0]}}],
                "effects": effects or [],
            }
        )
    )


BOX = {"name": "box", "primitive": {"box": [0.06, 0.08, 0.10]}, "pose": {"x_m": 0.0, "y_m": 0.0}}
CYL = {"name": "cyl", "primitive": {"cylinder": [0.03, 0.12]}, "pose": {"x_m": 0.0, "y_m": 0.0}}
TCP = grasp_to_tcp_pose(0.0, 0.0, 0.16 + 0.05, 0.0)  # gel centres 5 cm above the table


def test_box_contact_flat_press() -> None:
    w = make_world(BOX)
    c = w.grasp_contact(TCP, 10.0)
    expected = 10.0 / (K * GEL[0] * GEL[1])  # whole gel on a flat face: d = F / (k A)
    # the box is 8 cm across tool y; each finger presses in by d after touching
    assert c.width_m == pytest.approx(0.08 - 2 * expected * 1e-3, abs=1e-6)
    assert c.centre_shift_m == pytest.approx(0.0, abs=1e-7)
    for finger in ("left", "right"):
        f = c.fingers[finger]
        assert f.in_contact and not f.collision and not f.saturated
        assert f.indentation_mm == pytest.approx(expected, rel=1e-3)
        assert f.contact_area_mm2 == pytest.approx(GEL[0] * GEL[1], rel=1e-3)
        gap = c.gap_mm[finger]
        assert gap.shape == (120, 160) and gap.dtype == np.float32
        np.testing.assert_allclose(gap, -expected, atol=1e-4)
    # the contact gel frame sits on the box face, its +y pointing into the box
    left = c.fingers["left"].gel_to_world
    assert abs(abs(left[1, 3]) - (0.04 - expected * 1e-3)) < 1e-6
    assert np.dot(left[:3, 1], -left[:3, 3] * [0, 1, 0]) > 0


def test_force_scales_indentation() -> None:
    w = make_world(BOX)
    d5 = w.grasp_contact(TCP, 5.0).fingers["left"].indentation_mm
    d20 = w.grasp_contact(TCP, 20.0).fingers["left"].indentation_mm
    assert d20 == pytest.approx(4 * d5, rel=1e-3)  # linear on a flat face
    huge = w.grasp_contact(TCP, 500.0).fingers["left"]
    assert huge.saturated and huge.indentation_mm == pytest.approx(2.0)


def test_cylinder_contact_line_press() -> None:
    w = make_world(CYL)
    c = w.grasp_contact(TCP, 10.0)
    d_sim = c.fingers["left"].indentation_mm
    assert c.width_m == pytest.approx(0.06 - 2 * d_sim * 1e-3, abs=2e-5)
    # Winkler layer on a cylinder of radius R (axis along gel z, length L):
    # F = k L (4/3) sqrt(2R) d^1.5  ->  d, half-width sqrt(2 R d)
    R, L = 30.0, GEL[1]
    d = (10.0 / (K * L * (4 / 3) * np.sqrt(2 * R))) ** (2 / 3)
    f = c.fingers["left"]
    assert f.indentation_mm == pytest.approx(d, rel=0.03)
    assert f.contact_area_mm2 == pytest.approx(2 * np.sqrt(2 * R * d) * L, rel=0.05)
    gap = c.gap_mm["left"]
    x = (np.arange(160) - 79.5) * 0.1245  # columns run along gel x (across the cylinder axis)
    expected = R - np.sqrt(R**2 - x**2) - f.indentation_mm  # the circle
    np.testing.assert_allclose(gap[60, :], expected, atol=0.02)
    # constant along the cylinder axis (rows, gel z)
    assert np.ptp(gap[:, 80]) < 0.01


def test_gap_map_sizes() -> None:
    w = make_world(CYL)
    c = w.grasp_contact(TCP, 10.0, size=(100, 100), extent_mm=(12.45, 12.45))
    g = c.gap_mm["right"]
    assert g.shape == (100, 100)
    g2 = c.gap_map("right", (120, 160))
    assert g2.shape == (120, 160)
    assert g.min() == pytest.approx(g2.min(), abs=0.02)


def test_nothing_to_grasp() -> None:
    w = make_world(BOX)
    c = w.grasp_contact(grasp_to_tcp_pose(0.25, 0.2, 0.21, 0.0), 10.0)
    assert c.width_m == pytest.approx(0.0)
    for f in c.fingers.values():
        assert not f.in_contact
    assert np.all(np.isinf(c.gap_mm["left"]))


def test_open_finger_inside_object_is_a_collision() -> None:
    w = make_world({"name": "box", "primitive": {"box": [0.06, 0.2, 0.10]}, "pose": {"x_m": 0.0, "y_m": 0.0}})
    c = w.grasp_contact(TCP, 10.0)
    assert all(f.collision and not f.in_contact for f in c.fingers.values())


def test_relief_shows_in_the_gap() -> None:
    obj = dict(BOX, relief=[{"kind": "ridges", "pitch_mm": 2.0, "depth_mm": 0.2, "axis": [0, 0, 1]}])
    plain = make_world(obj).grasp_contact(TCP, 10.0).gap_mm["left"]
    ridged = make_world(obj, [{"name": "micro_relief"}]).grasp_contact(TCP, 10.0).gap_mm["left"]
    assert np.ptp(plain) < 1e-3
    # ridges vary along world z = gel z (rows) with a 2 mm pitch and 0.2 mm depth
    profile = ridged[:, 80]
    assert 0.15 < np.ptp(profile) < 0.25
    spectrum = np.abs(np.fft.rfft(profile - profile.mean()))
    freq = np.fft.rfftfreq(profile.size, d=0.1245)  # cycles per mm
    assert freq[np.argmax(spectrum)] == pytest.approx(0.5, abs=0.05)
    assert np.ptp(ridged[60, :]) < 0.02  # constant across


def test_off_centre_object_shifts_the_gripper_centre() -> None:
    w = make_world(dict(BOX, pose={"x_m": 0.0, "y_m": 0.01}))
    c = w.grasp_contact(TCP, 10.0)
    assert all(f.in_contact for f in c.fingers.values())
    # tool y = -world y for this grasp: the object centre sits 1 cm along -tool y
    assert c.centre_shift_m == pytest.approx(-0.01, abs=1e-6)
    assert c.width_m == pytest.approx(0.08 - 2 * c.fingers["left"].indentation_mm * 1e-3, abs=1e-6)


def test_contact_width_for_the_gripper() -> None:
    w = make_world(BOX)
    assert w.contact_width_m(TCP) == pytest.approx(0.08, abs=1e-6)
    assert w.contact_width_m(TCP, 10.0) < 0.08
    assert w.contact_width_m(grasp_to_tcp_pose(0.25, 0.2, 0.21, 0.0)) is None


def test_sphere_contact_point_press() -> None:
    # Winkler layer on a sphere of radius R: F = k pi R d^2 (contact radius sqrt(2 R d))
    w = make_world({"name": "ball", "primitive": {"sphere": 0.04}, "pose": {"x_m": 0.0, "y_m": 0.0}})
    tcp = grasp_to_tcp_pose(0.0, 0.0, 0.16 + 0.04, 0.0)  # gel centres at the ball's equator
    c = w.grasp_contact(tcp, 10.0)
    R = 40.0
    d = np.sqrt(10.0 / (K * np.pi * R))
    f = c.fingers["left"]
    assert f.in_contact and f.indentation_mm == pytest.approx(d, rel=0.02)
    assert f.contact_area_mm2 == pytest.approx(np.pi * 2 * R * d, rel=0.05)
    gap = c.gap_mm["left"].astype(np.float64)
    assert gap.min() == pytest.approx(-d, abs=0.01)
    assert c.width_m == pytest.approx(0.08 - 2 * f.indentation_mm * 1e-3, abs=1e-6)


@pytest.mark.parametrize("method", ["nearest_point", "surface"])
def test_depth_map_of_a_grasp_lines_up_with_what_the_gel_feels(method: str) -> None:
    """What the patch extractor computes from the object's model and the gripper's reading
    (symmetric gels at the held width, model centred between them) is, bin for bin, the gel
    gap the simulated GelSight renders from: same frame, same orientation, same place."""
    w = make_world(CYL)
    geometry = w.scene.gripper_geometry()
    params = DepthMapParams(shape=(60, 80), margin_m=0.002, y_range_m=(-0.005, 0.01), method=method)
    half_x, half_z, _, y_far = crop_bounds(geometry, params)
    # The cylinder's side where the gels can reach it, on a 0.1 mm grid.
    theta, z = np.meshgrid(np.arange(0, 2 * np.pi, 1e-4 / 0.03), np.arange(0.03, 0.07, 1e-4))
    model = np.column_stack([0.03 * np.cos(theta.ravel()), 0.03 * np.sin(theta.ravel()), z.ravel()])
    registered = np.eye(4)
    registered[1, 3] = 0.004  # registered 4 mm off along the closing axis
    tcp = grasp_to_tcp_pose(0.005, 0.0, 0.16 + 0.05, 0.0)  # 5 mm off the axis along the gels
    contact = w.grasp_contact(tcp, 10.0, size=(60, 80), extent_mm=(2e3 * half_z, 2e3 * half_x))
    gels = gel_poses_world(tcp, contact.width_m, geometry)
    gripper = w.scene.gripper
    centred = centre_between_gels(
        model, registered, gels["left"], gels["right"], geometry, 10.0, gripper.foundation_stiffness_n_per_mm3
    )
    for finger in ("left", "right"):
        gap_mm = contact.gap_mm[finger]
        depth_mm = contact_depth_map(model, centred, gels[finger], geometry, params).depth_map_m * 1e3
        pressed = gap_mm < 0
        assert 0.1 < pressed.mean() < 0.6
        # A nearest-point bin holds the minimum over its width, the gap map the value at its
        # centre: they may disagree on the bins the contact's edge crosses, and by a slope times
        # half a bin (measured: 1.2 % of bins, median 8 um, at most 90 um).
        assert np.mean((depth_mm < 0) != pressed) < 0.03
        assert np.median(np.abs(depth_mm[pressed] - gap_mm[pressed])) < 0.02
        assert np.all(depth_mm[np.isinf(gap_mm)] == np.float32(y_far * 1e3))
        if method == "surface":  # the surface at the bin's centre, as the gap map (measured: 0 %, 0.9, 3.2 um)
            seen = np.isfinite(gap_mm)
            assert np.mean((depth_mm < 0) != pressed) < 0.005
            assert np.median(np.abs(depth_mm[pressed] - gap_mm[pressed])) < 0.003
            assert np.abs(depth_mm[seen] - gap_mm[seen]).max() < 0.01


def test_an_object_is_placed_where_each_gel_presses_as_its_own_contact_needs() -> None:
    """A box's face toward one gel, a cylinder's side toward the other, held at 10 N: the world
    presses the gel on the narrow side three times deeper. Placed by the grasp force, the
    depth-maps are the gels' gaps on both sides (median within 10 um); placed so that both gels
    reach equally far (a force of 0, the rule before), each is 0.14 mm off."""
    box = {"name": "box", "primitive": {"box": [0.06, 0.04, 0.10]}, "pose": {"x_m": 0.0, "y_m": 0.02}}
    cylinder = {"name": "cyl", "primitive": {"cylinder": [0.03, 0.12]}, "pose": {"x_m": 0.0, "y_m": -0.03}}
    w = SimWorld(
        parse_scene(
            {
                "workspace": {"min_m": [-0.35, -0.3, 0.0], "max_m": [0.35, 0.3, 0.5]},
                "objects": [box, cylinder],
                "cameras": [{"name": "top", "pose": {"position_m": [0, 0, 1.0], "look_at_m": [0, 0, 0]}}],
            }
        )
    )
    geometry, stiffness = w.scene.gripper_geometry(), w.scene.gripper.foundation_stiffness_n_per_mm3
    params = DepthMapParams(shape=(60, 80), margin_m=0.002, y_range_m=(-0.005, 0.01), method="surface")
    half_x, half_z, _, _ = crop_bounds(geometry, params)
    tcp = grasp_to_tcp_pose(0.0, -0.01, 0.16 + 0.05, 0.0)
    contact = w.grasp_contact(tcp, 10.0, size=(60, 80), extent_mm=(2e3 * half_z, 2e3 * half_x))
    presses = {finger: contact.fingers[finger].indentation_mm for finger in ("left", "right")}
    assert presses["left"] > 2.5 * presses["right"]  # the cylinder's side, the box's face
    # The two surfaces the gels face, on a 0.1 mm grid: the box's face at y = 40 mm, the cylinder.
    x, z = np.meshgrid(np.arange(-0.03, 0.03, 1e-4), np.arange(0.03, 0.07, 1e-4))
    theta, zz = np.meshgrid(np.arange(0, 2 * np.pi, 1e-4 / 0.03), np.arange(0.03, 0.07, 1e-4))
    model = np.concatenate(
        [
            np.column_stack([x.ravel(), np.full(x.size, 0.04), z.ravel()]),
            np.column_stack([0.03 * np.cos(theta.ravel()), -0.03 + 0.03 * np.sin(theta.ravel()), zz.ravel()]),
        ]
    )
    registered = np.eye(4)
    registered[1, 3] = 0.004  # registered 4 mm off along the closing axis
    gels = gel_poses_world(tcp, contact.width_m, geometry)
    for force_n, within_mm in ((10.0, 0.01), (0.0, None)):
        centred = centre_between_gels(model, registered, gels["left"], gels["right"], geometry, force_n, stiffness)
        for finger in ("left", "right"):
            gap_mm = contact.gap_mm[finger]
            depth_mm = contact_depth_map(model, centred, gels[finger], geometry, params).depth_map_m * 1e3
            error_mm = np.median(np.abs(depth_mm[gap_mm < 0] - gap_mm[gap_mm < 0]))
            if within_mm is None:
                assert error_mm > 0.1
            else:
                assert error_mm < within_mm
