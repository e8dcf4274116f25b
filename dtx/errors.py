"""What a command does with a mistake the user can fix."""

from __future__ import annotations

import argparse
import functools
import sys
from collections.abc import Callable

Command = Callable[[argparse.Namespace], int]


def exit_1_on(*errors: type[BaseException]) -> Callable[[Command], Command]:
    """A command that meets one of ``errors`` (a bad file, a bad config) prints ``error: ...``
    on stderr and returns 1; any other exception is a bug and keeps its traceback."""

    def wrap(command: Command) -> Command:
        @functools.wraps(command)
        def run(args: argparse.Namespace) -> int:
            try:
                return command(args)
            except errors as err:
                print(f"error: {err}", file=sys.stderr)
                return 1

        return run

    return wrap
