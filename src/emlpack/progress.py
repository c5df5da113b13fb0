"""Progress of long work: the one helper every loop of the package and of ``emlp`` uses.

:func:`progress` returns a tqdm bar. On a terminal it is tqdm's own (count, rate, ETA); when
the stream is not a terminal (a log file, a pipe, a batch job's output) it writes a plain line
every ``every`` items and at the end instead, with the same count, rate and ETA and no
carriage returns::

    label: 40/120 (33%) 0:02:10 elapsed, 0:04:20 left, 0.31 conf/s

``enabled=False`` (a command's ``--quiet``) silences both. :func:`write` prints a line without
breaking a bar on the terminal. Torch-free (the labeling side uses it too).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Iterable
from typing import IO, Any

from tqdm import tqdm

__all__ = ["LINE_FORMAT", "LINES_PER_RUN", "progress", "write"]

#: the plain line's format (tqdm's ``format_meter`` fields)
LINE_FORMAT = ("{desc}: {n_fmt}/{total_fmt} ({percentage:.0f}%) {elapsed} elapsed,"
               " {remaining} left, {rate_fmt}{postfix}")
#: without ``every``: about this many plain lines in a run of known length
LINES_PER_RUN = 10


class _Lines(tqdm):
    """tqdm writing one plain line every ``miniters`` items and at the end (no bar, no
    carriage return): for a stream that is not a terminal. tqdm's documented hook for another
    front end is :meth:`display`; the rate is the run's average (``smoothing=0``)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._last_line = kwargs.get("initial", 0)  # nothing to say before the first item
        super().__init__(*args, **kwargs)

    def display(self, msg: str | None = None, pos: int | None = None) -> bool:
        closing = msg == ""  # tqdm's close(); a refresh (update, set_postfix) passes None
        due = self.n - self._last_line >= self.miniters
        if due or (closing and (self.n != self._last_line or self.total == 0)):
            self._last_line = self.n
            fmt = dict(self.format_dict)
            fmt["bar_format"] = LINE_FORMAT if fmt.get("total") else (
                "{desc}: {n_fmt} {elapsed} elapsed, {rate_fmt}{postfix}")
            fmt["prefix"] = fmt.get("prefix") or "progress"
            self.fp.write(self.format_meter(**fmt) + "\n")
            self.fp.flush()
        return False  # nothing on screen to clear (tqdm's close then writes no "\r")

    def clear(self, nolock: bool = False) -> None:
        """Nothing to clear: the lines stay."""

    def moveto(self, n: int) -> None:
        """No cursor movement in a plain stream."""


def progress(iterable: Iterable | None = None, *, total: int | None = None, desc: str = "",
             unit: str = "it", enabled: bool = True, every: int | None = None,
             file: IO[str] | None = None, leave: bool = True, initial: int = 0,
             lines: bool = True) -> tqdm:
    """A progress bar over ``iterable`` (or updated by hand: ``bar.update(n)``), on ``file``
    (default ``sys.stderr``, looked up at the call): tqdm's bar with rate and ETA on a
    terminal, else a plain line every ``every`` items (default: about :data:`LINES_PER_RUN`
    lines a run when ``total`` is known, else every item) and one at the end; nothing when
    ``enabled`` is false, nor off a terminal with ``lines=False`` (a loop whose caller logs a
    line per round itself, e.g. the trainer's per-epoch line). ``initial``: items done before
    (a resumed run); ``leave``: keep the terminal bar when done."""
    stream = sys.stderr if file is None else file
    if total is None and iterable is not None and hasattr(iterable, "__len__"):
        total = len(iterable)  # type: ignore[arg-type]
    common = {"total": total, "desc": desc, "unit": unit, "file": stream, "initial": initial}
    terminal = _is_terminal(stream)
    if not enabled or not (terminal or lines):
        return tqdm(iterable, disable=True, **common)
    if terminal:
        return tqdm(iterable, leave=leave, dynamic_ncols=True, **common)
    if every is None:
        left = (total or 0) - initial
        every = max(1, math.ceil(left / LINES_PER_RUN)) if left > 0 else 1
    # a line every `every` items, never on a timer (mininterval 0, no monitor thread)
    return _Lines(iterable, miniters=max(1, int(every)), mininterval=0.0,
                  maxinterval=float("inf"), smoothing=0.0, leave=False, **common)


def write(text: str, file: IO[str] | None = None) -> None:
    """Print ``text`` as a line on ``file`` (default ``sys.stderr``) without breaking a
    progress bar on the terminal (``tqdm.write``)."""
    tqdm.write(text, file=sys.stderr if file is None else file)


def _is_terminal(stream: IO[str]) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # a closed or foreign stream
        return False
