"""Progress reporting for long loops: items done, rate and time left, at most every few seconds."""

from __future__ import annotations

import logging
import time
from typing import Callable

logger = logging.getLogger("atlas_pipeline")

LogFn = Callable[[str], None]


class Progress:
    """Counts work items and logs ``"<label>: 40/100 frames (12.3 frames/s, about 5 s left)"``.

    Args:
        label: what is being done ("fusing frames").
        total: number of items, or None when unknown.
        log: where lines go; the library default is ``logging``, Dagster assets pass
            ``context.log.info`` so the lines show in the run log.
        every_s: minimum seconds between two lines (the last item always logs).
    """

    def __init__(self, label: str, total: int | None, log: LogFn | None = None,
                 every_s: float = 2.0, unit: str = "frames"):
        self.label = label
        self.total = total
        self.log = log or logger.info
        self.every_s = every_s
        self.unit = unit
        self.done = 0
        self.t0 = time.perf_counter()
        self._last = self.t0

    @property
    def elapsed_s(self) -> float:
        return time.perf_counter() - self.t0

    @property
    def rate(self) -> float:
        el = self.elapsed_s
        return self.done / el if el > 0 else 0.0

    def update(self, n: int = 1, extra: str = "") -> None:
        """Count ``n`` more items; ``extra`` is appended to the line (e.g. "3 lost")."""
        self.done += n
        now = time.perf_counter()
        finished = self.total is not None and self.done >= self.total
        if finished or now - self._last >= self.every_s:
            self._last = now
            of = f"/{self.total}" if self.total is not None else ""
            eta = self.eta_s
            left = f", about {format_duration(eta)} left" if (eta is not None and not finished) else ""
            tail = f", {extra}" if extra else ""
            self.log(f"{self.label}: {self.done}{of} {self.unit} ({self.rate:.1f} {self.unit}/s{left}{tail})")

    @property
    def eta_s(self) -> float | None:
        """Seconds left at the mean rate so far; None without a total or before the first item."""
        if self.total is None or self.done <= 0 or self.rate <= 0:
            return None
        return max(0.0, (self.total - self.done) / self.rate)


def format_duration(seconds: float) -> str:
    """``42 s``, ``3 min 5 s``, ``1 h 2 min``: how long, at a glance."""
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60} s"
    return f"{s // 3600} h {(s % 3600) // 60} min"
