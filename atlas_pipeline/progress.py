"""Progress reporting for long loops: items done, rate and time left.

Two outputs, both optional:

* ``log``: plain lines at most every few seconds (``logging`` by default; Dagster assets pass
  ``context.log.info`` so the lines land in the run log the web UI shows);
* a :class:`Terminal` (set by the command line with :func:`use_terminal`): a bar redrawn in place
  with ``\\r`` when the stream is a terminal, plain periodic lines when it is not (a log file, CI).

While a terminal is set, the library's default ``logging`` lines are left out (the terminal shows
the same), an explicit ``log`` still gets its lines (the Dagster run log keeps them).
"""

from __future__ import annotations

import contextlib
import logging
import shutil
import threading
import time
from typing import Callable, Iterator, TextIO

logger = logging.getLogger("atlas_pipeline")

LogFn = Callable[[str], None]

__all__ = ["Progress", "Terminal", "use_terminal", "current_terminal", "format_duration"]

DEFAULT_EVERY_S = 2.0  # plain log lines: at most one per 2 s per loop
BAR_REDRAW_S = 0.1  # a bar redrawn at most 10 times a second (redrawing costs the loop time)
PLAIN_EVERY_S = 10.0  # not a terminal (a file, CI): a line every 10 s keeps the log short
BAR_WIDTH = 24  # characters of the bar itself
MIN_LINE_WIDTH = 40  # narrower terminals (or unknown widths) still get a usable line
FINISH_REL_TOL = 1e-9
CLEAR_TO_EOL = "\x1b[K"  # ANSI "erase to end of line": what a shorter redraw leaves behind


def _count(x: float) -> str:
    """Whole counts as ``1,234``; fractional ones (megabytes) with one decimal."""
    return f"{x:,.0f}" if float(x).is_integer() else f"{x:,.1f}"


class Terminal:
    """Where bars are drawn: ``stream`` (stderr), a bar in place when it is a terminal
    (``is_tty``, detected by default), plain lines every ``plain_every_s`` otherwise. A finished
    bar is cleared unless ``keep_finished`` (the quiet command line prints a line per stage instead).

    One bar is drawn at a time; :meth:`write_line` clears it first, so log lines and bars do not
    run into each other (the bar comes back on its next update).
    """

    def __init__(self, stream: TextIO, is_tty: bool | None = None, plain_every_s: float = PLAIN_EVERY_S,
                 width: int | None = None, keep_finished: bool = False):
        self.stream = stream
        self.keep_finished = keep_finished
        if is_tty is None:
            isatty = getattr(stream, "isatty", None)
            is_tty = bool(isatty and isatty())
        self.is_tty = is_tty
        self.plain_every_s = plain_every_s
        self._width = width
        self._drawn = False  # a bar is on the current line
        self._lock = threading.Lock()
        enc = (getattr(stream, "encoding", None) or "").lower().replace("-", "")
        # block characters where the stream can encode them, ASCII elsewhere (LANG=C, pipes)
        self.fill, self.empty = ("█", "░") if enc.startswith("utf") else ("#", "-")

    @property
    def width(self) -> int:
        w = self._width or shutil.get_terminal_size((80, 24)).columns
        return max(MIN_LINE_WIDTH, w)

    def _write(self, text: str) -> None:
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):  # a closed or broken stream: progress is never worth a crash
            pass

    def draw(self, text: str) -> None:
        """Redraw the bar line (terminal) with ``text``, cut to the terminal's width."""
        with self._lock:
            self._write("\r" + text[: self.width - 1] + CLEAR_TO_EOL)
            self._drawn = True

    def finish(self, text: str) -> None:
        """The bar's last state: kept on screen (``keep_finished``), else cleared (a summary line,
        e.g. the stage's, follows)."""
        if not self.keep_finished:
            self.clear()
            return
        with self._lock:
            self._write("\r" + text[: self.width - 1] + CLEAR_TO_EOL + "\n")
            self._drawn = False

    def clear(self) -> None:
        """Remove a bar from the screen (an unfinished one: its loop stopped early or failed)."""
        with self._lock:
            if self._drawn:
                self._write("\r" + CLEAR_TO_EOL)
                self._drawn = False

    def write_line(self, text: str) -> None:
        """A whole line (a log record, a plain progress line), below any bar."""
        self.clear()
        with self._lock:
            self._write(text + "\n")


_terminal: Terminal | None = None


def current_terminal() -> Terminal | None:
    return _terminal


@contextlib.contextmanager
def use_terminal(terminal: Terminal | None) -> Iterator[Terminal | None]:
    """Draw progress on ``terminal`` inside the block (the command line sets stderr); the bar of
    a loop that did not finish is cleared at the end."""
    global _terminal
    before = _terminal
    _terminal = terminal
    try:
        yield terminal
    finally:
        if terminal is not None:
            terminal.clear()
        _terminal = before


class Progress:
    """Counts work items and reports ``"<label>: 40/100 frames (12.3 frames/s, about 5 s left)"``.

    Args:
        label: what is being done ("fusing frames").
        total: number of items, or None when unknown.
        log: where plain lines go; the library default is ``logging`` (left out while a
            :class:`Terminal` is set: it shows the same), Dagster assets pass ``context.log.info``
            so the lines show in the run log.
        every_s: minimum seconds between two plain log lines (the last item always logs).
        unit: what an item is ("frames", "steps", "MB").
    """

    def __init__(self, label: str, total: float | None, log: LogFn | None = None,
                 every_s: float = DEFAULT_EVERY_S, unit: str = "frames"):
        self.label = label
        self.total = total
        self.log = log or logger.info
        self._log_given = log is not None
        self.every_s = every_s
        self.unit = unit
        self.done: float = 0
        self.t0 = time.perf_counter()
        self._last = self.t0
        self._last_draw = -float("inf")
        self._last_plain = self.t0
        self._plain_lines = 0
        self._closed = False
        self._first: tuple[float, float] | None = None  # (time, count) of the first update

    @property
    def elapsed_s(self) -> float:
        return time.perf_counter() - self.t0

    @property
    def rate(self) -> float:
        """Items per second since the first update (the first item often carries a one-off cost,
        a JIT compile, that would make the time left look like an hour); overall before that."""
        if self._first is not None and self.done > self._first[1]:
            t1, d1 = self._first
            el = time.perf_counter() - t1
            if el > 0:
                return (self.done - d1) / el
        el = self.elapsed_s
        return self.done / el if el > 0 else 0.0

    @property
    def eta_s(self) -> float | None:
        """Seconds left at the mean rate so far; None without a total or before the first item."""
        if self.total is None or self.done <= 0 or self.rate <= 0:
            return None
        return max(0.0, (self.total - self.done) / self.rate)

    def line(self, extra: str = "", finished: bool = False) -> str:
        """The plain line: ``fusing frames: 40/100 frames (12.3 frames/s, about 5 s left, 3 lost)``."""
        of = f"/{_count(self.total)}" if self.total is not None else ""
        eta = self.eta_s
        left = f", about {format_duration(eta)} left" if (eta is not None and not finished) else ""
        took = f", {format_duration(self.elapsed_s)}" if finished else ""
        tail = f", {extra}" if extra else ""
        return f"{self.label}: {_count(self.done)}{of} {self.unit} ({self.rate:.1f} {self.unit}/s{left}{took}{tail})"

    def bar(self, terminal: Terminal, extra: str = "", finished: bool = False) -> str:
        """The terminal line: ``fusing frames  ████░░░░  40/100 frames  12.3 frames/s  ETA 5 s  3 lost``."""
        parts = [self.label]
        if self.total:
            frac = min(1.0, max(0.0, self.done / self.total))
            n = int(round(frac * BAR_WIDTH))
            parts.append(terminal.fill * n + terminal.empty * (BAR_WIDTH - n))
            parts.append(f"{_count(self.done)}/{_count(self.total)} {self.unit}")
        else:
            parts.append(f"{_count(self.done)} {self.unit}")
        parts.append(f"{self.rate:.1f} {self.unit}/s")
        eta = self.eta_s
        if finished:
            parts.append(f"in {format_duration(self.elapsed_s)}")
        elif eta is not None:
            parts.append(f"ETA {format_duration(eta)}")
        if extra:
            parts.append(extra)
        return "  ".join(parts)

    def update(self, n: float = 1, extra: str = "") -> None:
        """Count ``n`` more items; ``extra`` is appended to the line (e.g. "3 lost")."""
        self.done += n
        if self._closed:  # finished or closed: counted, not reported again
            return
        now = time.perf_counter()
        if self._first is None:
            self._first = (now, self.done)
        # a float total (megabytes) summed from chunks may end a rounding error short
        finished = self.total is not None and self.done >= self.total * (1 - FINISH_REL_TOL)
        term = _terminal
        if term is not None:
            self._to_terminal(term, now, extra, finished)
        if (term is None or self._log_given) and (finished or now - self._last >= self.every_s):
            self._last = now
            self.log(self.line(extra, finished))
        if finished:
            self._closed = True

    def _to_terminal(self, term: Terminal, now: float, extra: str, finished: bool) -> None:
        if term.is_tty:
            if finished:
                term.finish(self.bar(term, extra, finished=True))
            elif now - self._last_draw >= BAR_REDRAW_S:
                self._last_draw = now
                term.draw(self.bar(term, extra))
        elif now - self._last_plain >= term.plain_every_s or (finished and self._plain_lines):
            # periodic lines; the last one only when the loop was long enough to print any
            self._last_plain = now
            self._plain_lines += 1
            term.write_line(self.line(extra, finished))

    def close(self) -> None:
        """The loop ended (early stop, or fewer items than ``total``): a bar left unfinished is cleared."""
        if not self._closed:
            self._closed = True
            if _terminal is not None and _terminal.is_tty:
                _terminal.clear()

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def format_duration(seconds: float) -> str:
    """``42 s``, ``3 min 5 s``, ``1 h 2 min``: how long, at a glance."""
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60} s"
    return f"{s // 3600} h {(s % 3600) // 60} min"
