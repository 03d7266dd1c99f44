"""Named timing blocks (like TorchRL's `timeit`) and the process's age, for benchmarks that show where time goes.

    timer = Timer()
    with timer("iterate"):
        ...
    timer.totals  # {"iterate": seconds, ...}, in first-use order
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["Timer", "process_age"]

_IMPORTED_AT = time.monotonic()


class Timer:
    """Totals and counts of named `with timer(name):` blocks [s]."""

    def __init__(self) -> None:
        """Start with no blocks."""
        self.totals: dict[str, float] = {}
        self.counts: dict[str, int] = {}

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        """Time the block under `name` (added to earlier blocks of that name)."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.totals[name] = self.totals.get(name, 0.0) + time.perf_counter() - t0
            self.counts[name] = self.counts.get(name, 0) + 1

    def summary(self) -> str:
        """One line: 'name 1.23 s (n×), ...' in first-use order."""
        return ", ".join(f"{k} {v:.2f} s ({self.counts[k]}x)" for k, v in self.totals.items())


def process_age() -> float:
    """Seconds since this process started (Linux: from /proc, so the interpreter's own start-up counts; elsewhere
    since this module was imported)."""
    try:
        with open("/proc/self/stat") as f:
            # field 22 is the start time in clock ticks after boot; the command name (field 2) may hold spaces
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        return time.clock_gettime(time.CLOCK_BOOTTIME) - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, AttributeError):
        return time.monotonic() - _IMPORTED_AT
