"""Simulated backends: depth camera and GelSight deliver the bus messages."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.depth_camera.simulated import DepthCameraError, SimulatedDepthCamera, SimulatedDepthCameraConfig
from drivers.gelsight.simulated import SimulatedGelSight, SimulatedGelSightConfig
from msgs import DepthImage, TactileImage
from workcell.kinematics import grasp_to_tcp_pose


def test_depth_camera_uint16() -> None:
    cam = SimulatedDepthCamera(SimulatedDepthCameraConfig(scene="scenes/ycb_three.yaml", camera="right", pace=False))
    cam.connect()
    msg = cam.read()
    assert isinstance(msg, DepthImage)
    assert msg.depth.shape == (424, 512) and msg.depth.dtype == np.uint16
    assert msg.header.frame_id == "camera_right" and msg.header.seq == 1
    valid = msg.depth[msg.depth > 0]
    assert valid.size > 10000 and 500 <= valid.min() and valid.max() <= 4500
    assert msg.intrinsics.fx == pytest.approx(365.5)
    # reported extrinsic = nominal (the scene's offset effect stays hidden)
    np.testing.assert_allclose(msg.camera_to_world, cam.world.scene.camera("right").camera_to_world)
    assert not np.allclose(msg.camera_to_world, cam.world.true_camera_to_world("right"))
    cam.disconnect()


def test_depth_camera_float_ideal_matches_world() -> None:
    cam = SimulatedDepthCamera(SimulatedDepthCameraConfig(scene="scenes/ideal.yaml", output="float32_m", pace=False))
    cam.connect()
    msg = cam.read()
    assert msg.depth.dtype == np.float32
    np.testing.assert_array_equal(msg.depth, cam.world.render_depth("left"))
    np.testing.assert_array_equal(np.isnan(msg.depth_m()), np.isnan(msg.depth))


def test_depth_camera_pacing() -> None:
    import time

    cam = SimulatedDepthCamera(SimulatedDepthCameraConfig(scene="scenes/ideal.yaml", rate_hz=50.0))
    cam.connect()
    cam.read()
    t0 = time.monotonic()
    for _ in range(4):  # the first may be due at once; the next three wait a period each
        cam.read()
    assert time.monotonic() - t0 >= 3 / 50.0 - 0.005


def test_depth_camera_errors() -> None:
    cam = SimulatedDepthCamera(SimulatedDepthCameraConfig(scene="scenes/ideal.yaml", camera="middle", pace=False))
    with pytest.raises(DepthCameraError, match="middle"):
        cam.connect()
    with pytest.raises(DepthCameraError):
        SimulatedDepthCamera(SimulatedDepthCameraConfig(scene="scenes/ideal.yaml")).read()
    with pytest.raises(ValueError):
        SimulatedDepthCameraConfig(output="png")


def test_gelsight_contact_and_background() -> None:
    gs = SimulatedGelSight(SimulatedGelSightConfig(scene="scenes/ideal.yaml", sensor="left", pace=False))
    gs.connect()
    bg = gs.read()
    assert isinstance(bg, TactileImage) and bg.image.shape == (120, 160, 3) and bg.image.dtype == np.uint8
    np.testing.assert_array_equal(bg.image, bg.background)  # no contact, no effects
    # grasp the can (scene object 1 at the origin) halfway up
    can = gs.world.object_meshes[1][0]
    centre = 0.5 * (can.min(0) + can.max(0))
    tcp = grasp_to_tcp_pose(centre[0], centre[1], 0.16 + 0.06, 0.0)
    contact = gs.world.grasp_contact(tcp, 10.0)
    assert contact.fingers["left"].in_contact
    gs.observe_robot(tcp, contact.width_m, 10.0)
    touched = gs.read()
    assert touched.sensor == "left" and touched.header.frame_id == "gel_left"
    diff = np.abs(touched.image.astype(int) - bg.image.astype(int))
    assert diff.max() > 20
    assert np.min(gs.gap_mm()) < 0
    # gripper opened again: background
    gs.observe_robot(tcp, 0.11, 0.0)
    np.testing.assert_array_equal(gs.read().image, bg.background)
    # far from every object: nothing cast, nothing there
    gs.observe_robot(grasp_to_tcp_pose(0.3, 0.25, 0.4, 0.0), 0.05, 10.0)
    assert np.all(np.isinf(gs.gap_mm()))
    np.testing.assert_array_equal(gs.read().image, bg.background)


def test_a_frame_never_claims_a_time_the_robot_state_it_has_seen_cannot_vouch_for() -> None:
    # A gripper message that reaches the sensor late must not leave frames stamped after the
    # grip but rendered before it: stamps stop one state period after the last state seen.
    gs = SimulatedGelSight(
        SimulatedGelSightConfig(scene="scenes/ideal.yaml", sensor="left", pace=False, robot_state_period_s=0.05)
    )
    gs.connect()
    assert abs(gs.read().header.stamp_ns - time.time_ns()) < 5e9  # no state seen yet: the clock
    seen_ns = time.time_ns() - 2_000_000_000  # the last state was published 2 s ago
    gs.observe_robot(grasp_to_tcp_pose(0.3, 0.25, 0.4, 0.0), 0.11, 0.0, seen_ns)
    stamps = [gs.read().header.stamp_ns for _ in range(3)]
    assert stamps == [seen_ns + 50_000_000] * 3
    gs.observe_robot(grasp_to_tcp_pose(0.3, 0.25, 0.4, 0.0), 0.11, 0.0, time.time_ns() + 10**9)
    assert gs.read().header.stamp_ns <= time.time_ns()  # never ahead of the clock


def test_gelsight_native_and_large_size() -> None:
    gs = SimulatedGelSight(
        SimulatedGelSightConfig(
            scene="scenes/ideal.yaml", sensor="right", pace=False, image_height=480, image_width=640
        )
    )
    gs.connect()
    msg = gs.read()
    assert msg.image.shape == (480, 640, 3)
    assert msg.mm_per_px == pytest.approx(0.1245 / 4)


def test_a_still_gel_shows_the_frame_its_gap_draws() -> None:
    """The demo scene's GelSight effects carry no state: every frame of a still gel is the one
    the renderer draws for its gap with the gap's own generator, shown again, not re-drawn."""
    from sim.seeding import state_rng

    gs = SimulatedGelSight(SimulatedGelSightConfig(scene="scenes/ycb_three.yaml", sensor="left", pace=False))
    gs.connect()
    assert gs.renderer is not None and gs.world is not None
    untouched = np.full(gs.size, np.inf, np.float32)
    first, second = gs.read().image, gs.read().image
    np.testing.assert_array_equal(first, second)
    np.testing.assert_array_equal(first, gs.renderer.render(untouched, state_rng(untouched, gs.world.seed, 11, 0)))
    first[...] = 0  # a consumer's copy: the next frame is untouched by it
    np.testing.assert_array_equal(gs.read().image, second)


def test_gelsight_effects_from_scene_are_seeded() -> None:
    def frames(seed: int) -> list[np.ndarray]:
        gs = SimulatedGelSight(SimulatedGelSightConfig(scene="scenes/effects_gelsight.yaml", seed=seed, pace=False))
        gs.connect()
        return [gs.read().image for _ in range(2)]

    a, b, c = frames(1), frames(1), frames(2)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])
    assert not np.array_equal(a[0], a[1])  # the lighting drifts from frame to frame


def test_a_simulated_gelsight_frame_is_keyed_on_what_it_shows() -> None:
    """Whichever frame of a state a node takes, it is the same frame (sim.seeding); another
    state draws other noise, and coming back to a state gives its frame again."""
    gs = SimulatedGelSight(SimulatedGelSightConfig(scene="scenes/ycb_three.yaml", sensor="left", pace=False))
    gs.connect()
    untouched = [gs.read().image for _ in range(3)]
    assert all(np.array_equal(untouched[0], frame) for frame in untouched[1:])
    assert not np.array_equal(untouched[0], gs.read().background)  # the scene's sensor noise is there
    can = gs.world.object_meshes[1][0]
    centre = 0.5 * (can.min(0) + can.max(0))
    tcp = grasp_to_tcp_pose(centre[0], centre[1], 0.16 + 0.06, 0.0)
    contact = gs.world.grasp_contact(tcp, 10.0)
    gs.observe_robot(tcp, contact.width_m, 10.0)
    pressed = [gs.read().image for _ in range(2)]
    np.testing.assert_array_equal(pressed[0], pressed[1])
    gs.observe_robot(tcp, 0.11, 0.0)
    np.testing.assert_array_equal(gs.read().image, untouched[0])
