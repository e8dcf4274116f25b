"""The software version a fake UR controller runs, and what changes with it.

A lab may own a CB3 arm (PolyScope 3.x) or an e-Series one (PolyScope 5.x); what a client sees
differs in four ways, each taken from a public source:

- the dashboard server's ``PolyscopeVersion`` answers ``URSoftware <major>.<minor>.<bugfix>.<build>
  (<build date>)`` (Universal Robots, "Dashboard Server CB-Series, port 29999" and "Dashboard
  Server e-Series, port 29999", universal-robots.com how-tos 15690 and 42728); RTDE's
  "get URControl version" package reports the same four numbers (RTDE guide);
- a dashboard command exists from a version on, and a controller older than that answers
  ``could not understand: '<command>'`` like any unknown command. The first version of each
  command on CB3 and on e-Series is Universal Robots' own table in the Client Library
  (Universal_Robots_Client_Library, src/ur/dashboard_client_implementation_g5.cpp,
  ``g_command_list``): ``is in remote control`` from 5.6.0 and never on CB3, ``get serial
  number`` and ``get robot model`` from 3.12 / 5.6.0, ``safetystatus`` from 5.4.0 on e-Series
  only, ``restart safety`` from 3.7 / 5.1.0;
- only e-Series controllers have local and remote control (PolyScope 5 user manual, "Remote
  Control": in local control the controller does not receive and run programs sent over the
  network); CB3 has no such mode;
- RTDE streams at up to 125 Hz on CB3 and 500 Hz on e-Series (RTDE guide; ur_rtde picks the
  same two rates from the controller's major version, rtde_receive_interface.cpp).
"""

from __future__ import annotations

import dataclasses
import re

CB3_MAJOR, E_SERIES_MAJOR = 3, 5

# Command -> (first CB3 version, first e-Series version); None: never on that series.
DASHBOARD_COMMANDS_SINCE: dict[str, tuple[tuple[int, ...] | None, tuple[int, ...]]] = {
    "PolyscopeVersion": ((1, 8), (5, 0, 0)),
    "robotmode": ((1, 6), (5, 0, 0)),
    "running": ((1, 6), (5, 0, 0)),
    "programState": ((1, 8), (5, 0, 0)),
    "play": ((1, 4), (5, 0, 0)),
    "stop": ((1, 4), (5, 0, 0)),
    "quit": ((1, 4), (5, 0, 0)),
    "popup": ((1, 6), (5, 0, 0)),
    "close popup": ((1, 6), (5, 0, 0)),
    "power on": ((3, 0), (5, 0, 0)),
    "power off": ((3, 0), (5, 0, 0)),
    "brake release": ((3, 0), (5, 0, 0)),
    "safetymode": ((3, 0), (5, 0, 0)),
    "unlock protective stop": ((3, 1), (5, 0, 0)),
    "close safety popup": ((3, 1), (5, 0, 0)),
    "safetystatus": (None, (5, 4, 0)),
    "is in remote control": (None, (5, 6, 0)),
    "get serial number": ((3, 12), (5, 6, 0)),
    "get robot model": ((3, 12), (5, 6, 0)),
}


@dataclasses.dataclass(frozen=True)
class SoftwareVersion:
    """A controller's software version, e.g. ``SoftwareVersion.parse("5.4")`` (missing parts 0)."""

    major: int
    minor: int
    bugfix: int = 0
    build: int = 0

    @classmethod
    def parse(cls, text: str) -> "SoftwareVersion":
        """From "3.15", "5.4.2" or "5.11.1.108318"; a CB3 (3.x) or e-Series (5.x) version only."""
        if not re.fullmatch(r"\d+\.\d+(\.\d+){0,2}", text):
            raise ValueError(f"a UR software version looks like 3.15, 5.4.2 or 5.11.1.108318, got {text!r}")
        parts = [int(part) for part in text.split(".")]
        version = cls(*parts)
        if version.major not in (CB3_MAJOR, E_SERIES_MAJOR):
            raise ValueError(f"the fake controller runs CB3 (3.x) or e-Series (5.x) software, got {text!r}")
        return version

    @property
    def numbers(self) -> tuple[int, int, int, int]:
        return (self.major, self.minor, self.bugfix, self.build)

    @property
    def e_series(self) -> bool:
        return self.major >= E_SERIES_MAJOR

    @property
    def polyscope_version_line(self) -> str:
        """The dashboard's answer to ``PolyscopeVersion``; the build date is not modelled."""
        return f"URSoftware {'.'.join(map(str, self.numbers))} (fake controller)"

    @property
    def arm_model(self) -> str:
        """The arm it drives (workcell.ur_kinematics): a UR5 on CB3, a UR5e on e-Series, as
        ``get robot model`` answers "UR5" on both."""
        return "ur5e" if self.e_series else "ur5"

    @property
    def max_rtde_frequency_hz(self) -> float:
        return 500.0 if self.e_series else 125.0

    def has_dashboard_command(self, command: str) -> bool:
        """Whether this version's dashboard server knows ``command`` (a key of
        :data:`DASHBOARD_COMMANDS_SINCE`)."""
        cb3_since, e_series_since = DASHBOARD_COMMANDS_SINCE[command]
        since = e_series_since if self.e_series else cb3_since
        return since is not None and self.numbers >= since


# The version a fake runs unless told otherwise (a 2021 e-Series release).
DEFAULT_VERSION = SoftwareVersion(5, 11, 1, 108318)
