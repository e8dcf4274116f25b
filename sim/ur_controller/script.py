"""The fake UR controller's script server on port 30003, which receives the control script
``ur_rtde`` uploads (and uploads again after a protective stop is unlocked:
RTDEControlInterface::reuploadScript). A program starts when its top-level ``def ...():``
block ends; it does not interpret URScript: the controller core
(:meth:`sim.ur_controller.controller.Controller.start_program`) recognises ur_rtde's control
script and emulates what it does.
"""

from __future__ import annotations

import re
import socket

from sim.ur_controller.controller import Controller

SCRIPT_PORT = 30003


def serve_script(controller: Controller, sock: socket.socket) -> None:
    """The script server: a program starts when its top-level ``def ...():`` block ends."""
    program = ""
    try:
        while True:
            chunk = sock.recv(65536)
            if not chunk:
                break
            program += chunk.decode(errors="replace")
            while True:
                match = re.search(r"^def \w+\(\):\n.*?^end\s*$", program, re.S | re.M)
                if match is None:
                    break
                controller.start_program(match.group(0))
                program = program[match.end() :]
    except OSError:
        pass
    finally:
        sock.close()
