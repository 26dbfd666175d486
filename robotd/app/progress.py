"""A progress line on stderr for long commands run from a terminal (the demo)."""

from __future__ import annotations

import sys
import time


class Progress:
    """Robot time done and speed against real time, on stderr: one line rewritten in place
    on a terminal, else a line every 10 %."""

    def __init__(self, total_s: float, label: str = "demo") -> None:
        self.total_s = total_s
        self.label = label
        self.start = time.monotonic()
        self.last = 0.0
        self.tty = sys.stderr.isatty()
        self.next_pct = 10

    def update(self, sim_s: float, keyframes: int, final: bool = False) -> None:
        """Report ``sim_s`` seconds of robot time done and ``keyframes`` stored (at most
        twice a second, unless ``final``)."""
        now = time.monotonic()
        if not final and now - self.last < 0.5:
            return
        self.last = now
        wall = now - self.start
        pct = 100.0 * min(1.0, sim_s / self.total_s) if self.total_s > 0 else 100.0
        line = (f"{self.label}: {pct:5.1f}%  robot time {sim_s:6.1f}/{self.total_s:.0f} s  "
                f"keyframes {keyframes}  x{sim_s / wall if wall > 0 else 0:.1f} real time")
        if self.tty:
            sys.stderr.write("\r" + line + ("\n" if final else ""))
            sys.stderr.flush()
        elif final or pct >= self.next_pct:
            sys.stderr.write(line + "\n")
            while self.next_pct <= pct:
                self.next_pct += 10
