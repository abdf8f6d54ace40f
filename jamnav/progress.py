"""A one-line progress bar on stderr for long commands (redrawn in place on a terminal,
printed at most every few seconds otherwise, so logs stay readable)."""

from __future__ import annotations

import sys
import time


class ProgressBar:
    def __init__(self, label: str, total: int, stream=None, min_interval: float | None = None):
        self.label = label
        self.total = max(1, total)
        self.stream = stream or sys.stderr
        self.interactive = self.stream.isatty()
        self.min_interval = min_interval if min_interval is not None else (
            0.2 if self.interactive else 10.0)
        self.started = time.perf_counter()
        self.last = -1e9

    def update(self, done: int, note: str = "", force: bool = False) -> None:
        now = time.perf_counter()
        if not force and now - self.last < self.min_interval and done < self.total:
            return
        self.last = now
        elapsed = now - self.started
        rate = done / elapsed if elapsed > 0 else 0.0
        remaining = (self.total - done) / rate if rate > 0 else float("nan")
        width = 24
        filled = int(width * min(done, self.total) / self.total)
        bar = "#" * filled + "-" * (width - filled)
        line = (f"{self.label} [{bar}] {done}/{self.total} {rate:.1f}/s "
                f"eta {remaining:.0f}s {note}")
        if self.interactive:
            self.stream.write("\r" + line.ljust(100))
            if done >= self.total:
                self.stream.write("\n")
        else:
            self.stream.write(line + "\n")
        self.stream.flush()
