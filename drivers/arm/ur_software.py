"""What a UR controller's software version means for ``drivers.arm.ur``: CB3 (PolyScope 3.x)
or e-Series (5.x), the fastest RTDE rate, and whether it can say it is in remote control.

Sources: the dashboard server answers ``PolyscopeVersion`` with ``URSoftware
<major>.<minor>.<bugfix>.<build> (<date>)``, which ur_rtde's ``DashboardClient::polyscopeVersion``
cuts down to the four numbers (Universal Robots, "Dashboard Server CB-Series / e-Series, port
29999"). Only e-Series controllers have local and remote control, and their dashboard answers
``is in remote control`` from PolyScope 5.6.0 on (Universal Robots Client Library's dashboard
command table, dashboard_client_implementation_g5.cpp); ur_rtde sends the query only then and
otherwise warns and reads "not in remote control" (``DashboardClient::isInRemoteControl``), so
the backend must not ask an older controller. RTDE streams at up to 125 Hz on CB3 and 500 Hz
on e-Series (RTDE guide).
"""

from __future__ import annotations

import dataclasses
import re

from drivers.arm.base import ArmConnectionError

CB3_MAJOR, E_SERIES_MAJOR = 3, 5
REMOTE_CONTROL_QUERY_SINCE = (5, 6)
# The arms a CB3 controller drives; every other UR (UR3e to UR16e, UR20, UR30) runs PolyScope 5.
CB3_ARMS = ("ur3", "ur5", "ur10")


@dataclasses.dataclass(frozen=True)
class ControllerSoftware:
    """A controller's PolyScope version: major, minor, bugfix, build."""

    version: tuple[int, int, int, int]

    @classmethod
    def parse(cls, reply: str) -> "ControllerSoftware":
        """From ur_rtde's ``polyscopeVersion()`` ("5.4.0.0", or the whole reply when it holds no
        version); ArmConnectionError unless it is CB3 or e-Series software."""
        match = re.search(r"(\d+)\.(\d+)\.(\d+)\.(\d+)", reply)
        if match is None:
            raise ArmConnectionError(f"the UR dashboard answered PolyscopeVersion with {reply!r}, not a version")
        major, minor, bugfix, build = (int(part) for part in match.groups())
        software = cls((major, minor, bugfix, build))
        if major not in (CB3_MAJOR, E_SERIES_MAJOR):
            raise ArmConnectionError(
                f"{software.name}: this backend drives CB3 (PolyScope 3.x) and e-Series (PolyScope 5.x) controllers"
            )
        return software

    @property
    def name(self) -> str:
        return "PolyScope " + ".".join(str(part) for part in self.version)

    @property
    def series(self) -> str:
        return "e-Series" if self.version[0] == E_SERIES_MAJOR else "CB3"

    def check_arm_model(self, model: str) -> None:
        """ArmConnectionError unless ``model`` (whose DH parameters check joint targets) is an
        arm this controller's series drives: taken for a UR5e, a UR5 at its home pose is 5.6 cm lower."""
        if (model in CB3_ARMS) == (self.series == "CB3"):
            return
        if self.series == "CB3":
            fix = f"set the arm's model to the CB3 arm ({', '.join(CB3_ARMS)}), e.g. {model.removesuffix('e')}"
        else:
            fix = f"set the arm's model to the e-Series arm, e.g. {model}e"
        raise ArmConnectionError(
            f"model {model!r} is not among the arms {self.series} controllers drive ({self.name})", fix
        )

    @property
    def max_rtde_frequency_hz(self) -> float:
        return 500.0 if self.series == "e-Series" else 125.0

    @property
    def reports_remote_control(self) -> bool:
        """Whether the dashboard can say if the controller is in remote control."""
        return self.series == "e-Series" and self.version[:2] >= REMOTE_CONTROL_QUERY_SINCE

    @property
    def control_mode(self) -> str:
        """What is known about local and remote control, for people."""
        if self.series == "CB3":
            return "CB3: no local or remote control mode"
        if self.reports_remote_control:
            return "e-Series: in remote control"
        return "e-Series before 5.6: cannot report local or remote control"

    @property
    def script_fix(self) -> str:
        """What to check when the control script does not start."""
        if self.series == "CB3":
            return "check that no popup is open on the pendant"
        if self.reports_remote_control:
            return "check that the pendant is in remote control and no popup is open"
        return f"check that the pendant is in remote control ({self.name} cannot report it) and no popup is open"
