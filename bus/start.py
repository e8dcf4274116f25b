"""How the launcher starts a node: ``python -m bus.start MODULE ARGS...`` runs MODULE as
``python -m MODULE ARGS...`` does, except that a stop (SIGINT, SIGTERM) that comes while the
node is still starting ends it quietly, with status 0 as for any stop it was asked for.

A stop can come at any moment of a start-up: the launcher stops the graph a node was just
(re)started in, or Ctrl-C reaches the whole process group. Python's own SIGINT handler would
raise KeyboardInterrupt wherever the node happens to be (importing its libraries, connecting
its device) and print its traceback; SIGTERM would kill it with status -15. This module
imports nothing of the project, so its handler is in place before the node's imports begin;
the launcher starts the interpreter with both signals blocked (:func:`hold_stops`), so one that
comes even before this module runs waits for it. ``bus.node.run_node`` replaces the handler
with a clean shutdown once the node is made.
"""

from __future__ import annotations

import runpy
import signal
import sys
from types import FrameType

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def stop_quietly(signum: int, frame: FrameType | None) -> None:
    """A signal handler for a process that has nothing to save yet: end it with status 0."""
    raise SystemExit(0)


def hold_stops() -> None:
    """Block the stop signals (for a child, before it runs Python): one that comes during the
    interpreter's own start-up then waits for :func:`main`'s handler instead of printing a
    traceback."""
    signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)


def main() -> None:
    for signum in STOP_SIGNALS:
        signal.signal(signum, stop_quietly)
    # The node's own threads and children must take signals as usual.
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    if len(sys.argv) < 2:
        raise SystemExit("usage: python -m bus.start MODULE [ARGS...]")
    module = sys.argv.pop(1)
    runpy.run_module(module, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
