"""Simulated GelSight: renders the contact of its finger with the scene through
``sim.gelsight.GelSightRenderer`` (with the scene's GelSight effects).

The node tells the sensor where the robot is with :meth:`SimulatedGelSight.observe_robot`
(latest TCP pose, gripper width and grasp force); :meth:`SimulatedGelSight.read` then
returns the tactile image of the current contact, or of the untouched gel when the finger
touches nothing.

Contact rule: with a positive force and the gripper closed to (about) the width at which
the fingers meet the object, the gel presses in as ``SimWorld.grasp_contact`` computes
(the force on the gel's compliance); otherwise the gel sits where the kinematics put it and
only geometry counts (no press).
"""

from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING

import numpy as np

from drivers import requires_connection
from drivers.gelsight.base import GelSight, GelSightError
from msgs import Header, TactileImage
from sim.seeding import state_rng
from workcell.kinematics import gel_poses_world
from workcell.scene import SceneError

if TYPE_CHECKING:
    from sim.gelsight import GelSightRenderer
    from sim.grasp_contact import GraspContact
    from sim.world import SimWorld

__all__ = ["SimulatedGelSight", "SimulatedGelSightConfig", "GelSightError"]

SENSORS = ("left", "right")


@dataclasses.dataclass
class SimulatedGelSightConfig:
    scene: str = "scenes/ycb_three.yaml"
    sensor: str = "left"
    seed: int | None = None  # default: the scene's seed
    rate_hz: float = 30.0
    pace: bool = True  # read() waits for the next frame time, like the real camera
    image_height: int | None = None  # default: the scene's gelsight.image_height
    image_width: int | None = None
    width_tolerance_m: float = 0.002  # gripper within this of the contact width = holding
    # Period of the robot state the sensor follows (nodes.gripper publishes /gripper/state at
    # 20 Hz): a frame cannot claim a time later than this after the last state it has seen.
    robot_state_period_s: float = 0.05

    def __post_init__(self) -> None:
        if self.sensor not in SENSORS:
            raise ValueError(f"sensor {self.sensor!r} not one of {SENSORS}")
        if not (np.isfinite(self.rate_hz) and 0.0 < self.rate_hz <= 1000.0):
            raise ValueError(f"rate_hz {self.rate_hz} outside (0, 1000]")
        if not (np.isfinite(self.robot_state_period_s) and 0.0 < self.robot_state_period_s <= 10.0):
            raise ValueError(f"robot_state_period_s {self.robot_state_period_s} outside (0, 10] s")


class SimulatedGelSight(GelSight):
    def __init__(self, config: SimulatedGelSightConfig):
        self.config = config
        self.world: SimWorld | None = None
        self.renderer: GelSightRenderer | None = None
        self._gap: np.ndarray | None = None
        self._robot: tuple | None = None
        self._seq = 0
        self._next_t = 0.0
        self._known_until_ns: int | None = None  # the sensor knows the robot up to this time
        # The last frame drawn and the gap it shows: without an effect that carries state from
        # frame to frame, a frame is a function of its gap (its noise is keyed on it), and
        # between two robot states every frame shows the same gap.
        self._drawn: tuple[np.ndarray, np.ndarray] | None = None
        self.last_contact: GraspContact | None = None  # the last contact used (ground truth)

    def connect(self) -> None:
        from sim.gelsight import scene_renderer  # noqa: PLC0415 - Open3D loads on connect
        from sim.world import shared_world  # noqa: PLC0415 - Open3D loads on connect

        try:
            world = shared_world(self.config.scene, self.config.seed)
        except SceneError as exc:
            raise GelSightError(str(exc)) from exc
        gs = world.scene.gelsight
        self.size = (self.config.image_height or gs.image_height, self.config.image_width or gs.image_width)
        self.extent_mm = world.default_extent_mm()
        renderer = scene_renderer(world.scene, self.size)
        # the image covers the same field of view on the gel whatever its pixel count
        self.mm_per_px = renderer.pixel_pitch_mm[1]
        self._background = renderer.background()
        self._untouched = np.full(self.size, np.inf, dtype=np.float32)
        self._gap, self._drawn = None, None
        self._frames_carry_state = any(getattr(effect, "carries_state", True) for effect in renderer.effects)
        self._next_t = time.monotonic()
        self.world, self.renderer = world, renderer

    def disconnect(self) -> None:
        self.world = None
        self.renderer = None

    @property
    def is_connected(self) -> bool:
        return self.renderer is not None

    @requires_connection
    def observe_robot(
        self, tcp_pose_world: np.ndarray, gripper_width_m: float, force_n: float, stamp_ns: int | None = None
    ) -> None:
        """Latest robot state: TCP pose (UR pose, world), gripper width (m), grasp force (N), and
        when the state was published (``stamp_ns``, wall clock ns; None: no bound on frames)."""
        if stamp_ns is not None:
            self._known_until_ns = int(stamp_ns) + int(self.config.robot_state_period_s * 1e9)
        pose = np.asarray(tcp_pose_world, dtype=np.float64)
        key = (pose.tobytes(), float(gripper_width_m), float(force_n))
        if key == self._robot:
            return
        self._robot = key

        assert self.world is not None  # requires_connection
        scene = self.world.scene
        sensor = self.config.sensor
        if force_n > 0:
            contact = self.world.grasp_contact(pose, force_n, self.size, self.extent_mm, gap_fingers=(sensor,))
            fc = contact.fingers[sensor]
            if fc.in_contact and gripper_width_m <= contact.width_m + self.config.width_tolerance_m:
                self.last_contact = contact
                self._gap = contact.gap_mm[sensor]
                return
        width = float(np.clip(gripper_width_m, 0.0, scene.gripper.max_width_m))
        gel = gel_poses_world(pose, width, scene.gripper_geometry())[sensor]
        self.last_contact = None
        if self.world.near_gel(gel, self.extent_mm):
            self._gap = self.world.gap_map(gel, self.size, self.extent_mm)
        else:  # nothing within reach of the gel: no cast needed
            self._gap = np.full(self.size, np.inf, dtype=np.float32)

    def gap_mm(self) -> np.ndarray | None:
        """The gel gap map of the current state (mm; None before any observe_robot). When no
        object comes within 1 cm of the gel it is all +inf (the cast is skipped)."""
        return None if self._gap is None else self._gap.copy()

    @requires_connection
    def read(self) -> TactileImage:
        if self.config.pace:
            now = time.monotonic()
            if self._next_t > now:
                time.sleep(self._next_t - now)
            self._next_t = max(self._next_t, now) + 1.0 / self.config.rate_hz
        # Stamped when the frame is taken, as a camera stamps its exposure, but never later than
        # the robot state the sensor has seen can vouch for: a real gel presses the moment the
        # fingers close, this one only once the gripper's message has reached its node, which on
        # a loaded machine can trail the collector's copy of it by more than the settling time.
        stamp_ns = time.time_ns()
        if self._known_until_ns is not None:
            stamp_ns = min(stamp_ns, self._known_until_ns)
        # nothing presses: the untouched gel (through the renderer so its effects apply)
        gap = self._untouched if self._gap is None or not np.any(self._gap < 0) else self._gap
        if self._drawn is None or self._drawn[0] is not gap or self._frames_carry_state:
            # The frame's noise is keyed on the gap it shows (sim.seeding): whichever frame of a
            # grasp the collector takes, the same grasp gives the same image.
            assert self.world is not None and self.renderer is not None  # requires_connection
            rng = state_rng(gap, self.world.seed, 11, SENSORS.index(self.config.sensor))
            self._drawn = (gap, self.renderer.render(gap, rng))
        image = self._drawn[1].copy()
        self._seq += 1
        header = Header(stamp_ns=stamp_ns, seq=self._seq, frame_id=f"gel_{self.config.sensor}")
        return TactileImage(
            header=header,
            image=image,
            background=self._background.copy(),
            sensor=self.config.sensor,
            mm_per_px=float(self.mm_per_px),
        )
