"""The progress of a long step, readable wherever its output goes.

On a terminal a tqdm bar redraws itself in place. Anywhere else (a log file, a pipe, the
launcher's relay) each redraw is a carriage return and the whole bar again, thousands of them on
one "line": ``make demo > log`` was half a megabyte of them. There a step prints a plain line
instead, each time another tenth of the work is done or 10 s have passed since its last line,
whichever comes first, and a last one when it ends:

    train: 1200/2400 steps (50 %), 4.1 steps/s, ETA 4 min 53 s | g_l1 0.0412

A node under ``dtx launch`` writes into the launcher's relay, never to the terminal itself; the
launcher tells it in ``DTX_TERMINAL`` whether its own output is one.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from typing import TextIO, TypeVar

import numpy as np
from tqdm import tqdm

TERMINAL_ENV = "DTX_TERMINAL"
MARKS_PER_TASK = 10  # a line at each tenth of the work
LINE_EVERY_S = 10.0  # and at least this often while the work goes on
MAX_LINE = 300
# The largest total: every count up to it is a float exactly, so the rate, share and ETA are
# figures, never an OverflowError (10**400 steps) or a count rounded away (2**53 + 1 steps).
MAX_TOTAL = 2**53

T = TypeVar("T")


def on_terminal(stream: TextIO) -> bool:
    """Whether ``stream`` ends on a terminal: as ``DTX_TERMINAL`` says ("1" or "0") when the
    launcher set it, else as the stream itself says."""
    told = os.environ.get(TERMINAL_ENV)
    if told is not None:
        return told == "1"
    return stream.isatty()


def duration(seconds: float) -> str:
    """``seconds`` as a person reads it: "42 s", "4 min 53 s", "1 h 02 min"."""
    whole = round(seconds)
    if whole < 60:
        return f"{whole} s"
    if whole < 3600:
        return f"{whole // 60} min {whole % 60:02d} s"
    return f"{whole // 3600} h {whole % 3600 // 60:02d} min"


class Progress:
    """``total`` units of work done ``update`` by ``update``: a tqdm bar on a terminal, plain
    lines at a steady pace elsewhere (see the module's docstring).

    ``bar_on_terminal=False`` prints a plain line at every update on a terminal instead of a
    bar, for a process whose output is relayed line by line (the collector under the launcher).
    ``clock`` is injectable so the pacing can be tested without waiting."""

    def __init__(
        self,
        what: str,
        total: int,
        unit: str,
        *,
        initial: int = 0,
        enabled: bool = True,
        stream: TextIO | None = None,
        bar_on_terminal: bool = True,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not (_is_count(total) and total <= MAX_TOTAL):
            raise ValueError(f"{what}: progress needs a total that is an integer in [0, 2**53], got {_shown(total)}")
        if not (_is_count(initial) and initial <= total):
            raise ValueError(
                f"{what}: progress needs 0 <= initial <= total, got {_shown(initial)} of {total} (integers)"
            )
        total, initial = int(total), int(initial)
        self.what, self.total, self.unit, self.done = what, total, unit, initial
        self.enabled = enabled
        self._stream = sys.stderr if stream is None else stream
        self._clock = clock
        self._initial, self._started, self._note = initial, clock(), ""
        terminal = enabled and on_terminal(self._stream)
        self._bar = (
            tqdm(total=total, initial=initial, desc=what, unit=unit, file=self._stream)
            if terminal and bar_on_terminal
            else None
        )
        self._every_update = terminal and not bar_on_terminal
        self._lines, self._line_done, self._line_at = 0, initial, self._started
        self._next_mark = self._mark_after(initial)

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def note(self, text: str) -> None:
        """What the next lines say after the figures (losses, counts); the bar's postfix."""
        self._note = text
        if self._bar is not None:
            self._bar.set_postfix_str(text, refresh=False)

    def update(self, n: int = 1) -> None:
        """``n`` more units done."""
        self.done += n
        if self._bar is not None:
            self._bar.update(n)
            return
        if not self.enabled or self.done >= self.total:
            return  # the last line is close()'s, with the time taken
        if self._every_update or self.done >= self._next_mark or self._clock() - self._line_at >= LINE_EVERY_S:
            self._print_line()

    def close(self) -> None:
        """The last line (how far it got and in what time), unless the last one said it all."""
        if self._bar is not None:
            self._bar.close()
        elif self.enabled and (self._lines == 0 or self.done != self._line_done):
            self._print_line()

    def line(self) -> str:
        """Where the work stands, in one line of at most ``MAX_LINE`` characters."""
        elapsed = self._clock() - self._started
        rate = (self.done - self._initial) / elapsed if elapsed > 0 else 0.0
        share = f" ({100 * self.done / self.total:.0f} %)" if self.total else ""
        if self.done >= self.total:
            when = f"done in {duration(elapsed)}"
        else:
            when = f"ETA {duration((self.total - self.done) / rate)}" if rate > 0 else "ETA ?"
        speed = f"{rate:.1f} {self.unit}/s" if rate >= 1 else f"{60 * rate:.1f} {self.unit}/min"
        text = f"{self.what}: {self.done}/{self.total} {self.unit}{share}, {speed}, {when}"
        if self._note:
            text += f" | {self._note}"
        return text if len(text) <= MAX_LINE else text[: MAX_LINE - 3] + "..."

    def _print_line(self) -> None:
        print(self.line(), file=self._stream, flush=True)
        self._lines += 1
        self._line_done, self._line_at = self.done, self._clock()
        self._next_mark = self._mark_after(self.done)

    def _mark_after(self, done: int) -> int:
        """The first tenth of the total past ``done`` (the total itself after the last)."""
        if self.total == 0:
            return 1
        tenth = min(done * MARKS_PER_TASK // self.total + 1, MARKS_PER_TASK)
        return -(-self.total * tenth // MARKS_PER_TASK)


def _is_count(value: object) -> bool:
    return bool(isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= 0)


def _shown(value: object) -> str:
    """``value`` for an error message, bounded (an int past 4,300 digits has no repr at all)."""
    if isinstance(value, int) and value.bit_length() > 64:
        return f"an integer of {value.bit_length()} bits"
    return repr(value)[:80]


def track(items: Sequence[T], what: str, unit: str, enabled: bool = True) -> Iterator[T]:
    """Each of ``items`` in turn, with a :class:`Progress` of them on stderr."""
    with Progress(what, len(items), unit, enabled=enabled) as progress:
        for item in items:
            yield item
            progress.update()
