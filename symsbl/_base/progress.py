"""Progress of long steps on a terminal, silent everywhere else.

Simulating long records, accumulating the dictionary's Gram matrix chunk by chunk, drawing a
Monte Carlo band and scanning the discrepancy catalogue can each take seconds to minutes. They
report through :class:`Progress`, which writes one self-overwriting line to standard error when

- standard error is a terminal (a log file, a pipe, a notebook cell or CI stays clean),
- the step has already run for ``delay`` seconds (short steps never flicker),
- it runs in the main thread and no other progress line is open (a simulation inside a Monte
  Carlo band, or a fit inside a batch on worker threads, stays silent), and
- progress has not been switched off with :func:`set_progress` (``symsbl ... --quiet`` does this).

Examples
--------
>>> import io
>>> stream = io.StringIO()                     # not a terminal: nothing is written
>>> with Progress("simulate", total=3, stream=stream) as bar:
...     for _ in range(3):
...         bar.update()
>>> stream.getvalue()
''
>>> with progress_enabled(True):               # forced on, shown at once (delay=0)
...     with Progress("simulate", total=4, unit="steps", stream=stream, delay=0.0) as bar:
...         bar.update(4)
>>> stream.getvalue().splitlines()[-1].split(" in ")[0]
'simulate: 4/4 steps'
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Iterator

from .errors import ParameterError, expected

__all__ = ["Progress", "set_progress", "progress_enabled", "stopwatch"]

#: Seconds a step runs before its line appears (the default of :class:`Progress`'s ``delay``).
DELAY = 0.5
#: Minimum seconds between two redraws of a line (the default of ``interval``).
INTERVAL = 0.1

#: None: automatic (shown when standard error is a terminal); True/False: forced on/off.
_SETTING: bool | None = None
_OPEN = threading.local()


def set_progress(enabled: bool | None) -> bool | None:
    """Switch progress lines on (True), off (False) or back to automatic (None).

    Parameters
    ----------
    enabled : bool or None
        None shows progress only when standard error is a terminal.

    Returns
    -------
    bool or None
        The previous setting, to restore it later.

    Examples
    --------
    >>> import symsbl
    >>> previous = symsbl.set_progress(False)   # no progress lines, even on a terminal
    >>> symsbl.set_progress(previous)           # back to automatic
    False
    """
    global _SETTING
    if enabled is not None and not isinstance(enabled, bool):
        raise ParameterError(expected("enabled", "True, False or None", enabled))
    previous, _SETTING = _SETTING, enabled
    return previous


@contextlib.contextmanager
def progress_enabled(enabled: bool | None) -> Iterator[None]:
    """Context manager form of :func:`set_progress`; the previous setting is restored on exit.

    Examples
    --------
    >>> import symsbl
    >>> with symsbl.progress_enabled(False):
    ...     traj = symsbl.simulate(symsbl.systems.linear(), symsbl.time_grid(0.1, 1000))
    """
    previous = set_progress(enabled)
    try:
        yield
    finally:
        set_progress(previous)


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # closed or not a file
        return False


class Progress:
    """A one-line progress report for a loop of known (or unknown) length.

    Parameters
    ----------
    label : str
        What is running, e.g. ``"simulate duffing (rk4)"``.
    total : int, optional
        Number of units of work; None when unknown (a generator of chunks): the count is shown.
    unit : str
        Name of the unit (``"samples"``, ``"draws"``).
    stream : file-like, optional
        Where to write; standard error by default (looked up when the step starts).
    delay : float, optional
        Seconds a step must run before its line appears; :data:`DELAY` by default.
    interval : float, optional
        Minimum seconds between redraws; :data:`INTERVAL` by default.

    Notes
    -----
    Use it as a context manager; :meth:`update` is cheap (one clock read) when nothing is drawn.
    The closing line ends in ``(done)`` when the count reached ``total`` (or no total was
    given) and ``(stopped)`` otherwise: an exception, a simulation that diverged. A stream that
    fails while writing (a closed or hung-up terminal) ends the display, never the work.
    """

    def __init__(
        self,
        label: str,
        total: int | None = None,
        *,
        unit: str = "",
        stream=None,
        delay: float | None = None,
        interval: float | None = None,
    ):
        self.label, self.total, self.unit = label, total, unit
        self.delay = DELAY if delay is None else delay
        self.interval = INTERVAL if interval is None else interval
        self.count = 0
        self._stream = stream
        self._start = self._last = 0.0
        self._active = False
        self._shown = False

    def __enter__(self) -> Progress:
        stream = sys.stderr if self._stream is None else self._stream
        self._stream = stream
        outer = getattr(_OPEN, "depth", 0)
        enabled = _SETTING if _SETTING is not None else _is_terminal(stream)
        self._active = bool(enabled) and outer == 0 and threading.current_thread() is threading.main_thread()
        self._start = self._last = time.perf_counter()
        _OPEN.depth = outer + 1
        if self._active and self.delay <= 0:
            self._draw(self._start)
        return self

    def update(self, n: int = 1) -> None:
        """Record ``n`` more units of work done."""
        self.count += n
        if not self._active:
            return
        now = time.perf_counter()
        if now - self._start >= self.delay and (now - self._last >= self.interval or not self._shown):
            self._draw(now)

    def _text(self, now: float) -> str:
        unit = f" {self.unit}" if self.unit else ""
        if self.total:
            share = min(1.0, self.count / self.total)
            text = f"{self.label}: {self.count}/{self.total}{unit} ({100 * share:.0f} %), {now - self._start:.1f} s"
            if 0 < share < 1:
                text += f", about {(now - self._start) * (1 - share) / share:.0f} s left"
            return text
        return f"{self.label}: {self.count}{unit}, {now - self._start:.1f} s"

    def _write(self, text: str) -> None:
        """Write to the stream; a stream that fails (closed, hung-up terminal) ends the display, never the work."""
        try:
            self._stream.write(text)
            self._stream.flush()
        except (OSError, ValueError, AttributeError):
            self._active = self._shown = False

    def _draw(self, now: float) -> None:
        self._shown = True
        self._write("\r" + self._text(now) + "\033[K")
        self._last = now

    def __exit__(self, *exc) -> None:
        _OPEN.depth -= 1
        if self._shown:
            now = time.perf_counter()
            unit = f" {self.unit}" if self.unit else ""
            done = f"{self.count}/{self.total}" if self.total else f"{self.count}"
            finished = exc[0] is None and (not self.total or self.count >= self.total)
            status = "done" if finished else "stopped"
            self._write(f"\r{self.label}: {done}{unit} in {now - self._start:.1f} s ({status})\033[K\n")


def stopwatch():
    """A function that returns the seconds since the call that made it."""
    start = time.perf_counter()
    return lambda: time.perf_counter() - start
