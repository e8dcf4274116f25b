"""The simulated gripper: the real WSG-50 client talking to the firmware simulator on a pty.

Nothing is short-cut: every command crosses the same framing, CRC and status handling as
on the lab's serial line, so the simulation exercises the driver the lab runs.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

from drivers.gripper.firmware import GripperFirmware, Strictness
from drivers.gripper.wsg50 import WSG50Config, WSG50Gripper


@dataclasses.dataclass
class SimulatedGripperConfig:
    """Firmware limits (m, m/s, N), starting opening (m) and the client's time-outs (s)."""

    max_width_m: float = 0.110
    max_speed_m_s: float = 0.42
    max_force_n: float = 80.0
    initial_width_m: float = 0.110
    response_timeout_s: float = 0.3
    motion_timeout_s: float = 10.0
    frame_id: str = "tcp"
    time_scale: float = 1.0  # finger motions in wall time (0: instantaneous)
    # The web interface's clamping travel (m): a grasp finds the part only this close to the
    # nominal width it is given (firmware.Strictness); None: anywhere on the way.
    clamping_travel_m: float | None = 0.010
    referenced: bool = True  # False: starts as a gripper that still has to be homed


class SimulatedGripper(WSG50Gripper):
    """``contact_width_m()`` (m, or None when nothing is between the fingers) comes from the
    simulated world; the firmware asks it when a grasp or a closing move starts."""

    def __init__(
        self, config: SimulatedGripperConfig, contact_width_m: Callable[[], float | None] = lambda: None
    ) -> None:
        self._firmware = GripperFirmware(
            contact_width_m,
            max_width_m=config.max_width_m,
            max_speed_m_s=config.max_speed_m_s,
            max_force_n=config.max_force_n,
            initial_width_m=config.initial_width_m,
            time_scale=config.time_scale,
            strictness=Strictness(clamping_travel_m=config.clamping_travel_m, referenced=config.referenced),
        )
        super().__init__(
            WSG50Config(
                port=self._firmware.port,
                response_timeout_s=config.response_timeout_s,
                motion_timeout_s=config.motion_timeout_s,
                frame_id=config.frame_id,
                max_width_m=config.max_width_m,
                max_speed_m_s=config.max_speed_m_s,
                max_force_n=config.max_force_n,
            )
        )

    def connect(self) -> None:
        self._firmware.start()
        super().connect()

    def disconnect(self) -> None:
        super().disconnect()
        self._firmware.close()
