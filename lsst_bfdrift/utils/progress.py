"""A minimal progress bar for long runs (stderr; quiet when disabled)."""

import sys
import time

__all__ = ["ProgressBar"]


class ProgressBar:
    """Text progress bar: ``with ProgressBar(total, "label") as bar: bar(1)``.

    On a terminal the bar is redrawn in place; otherwise a line is printed at
    every 10 % so that logs stay short. ``enabled=False`` makes it silent.
    """

    def __init__(self, total, label="", *, enabled=True, stream=None, width=30):
        self.total = max(int(total), 1)
        self.label = label
        self.enabled = bool(enabled)
        self.stream = sys.stderr if stream is None else stream
        self.width = width
        self.done = 0
        self._last_decile = -1
        self._start = time.perf_counter()
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())

    def __call__(self, n=1):
        self.done = min(self.done + n, self.total)
        if self.enabled:
            self._draw()

    def _eta(self, frac, elapsed):
        """' ETA 12s' while running (elapsed / done x left), '' at the ends."""
        if not 0 < frac < 1:
            return ""
        return f" ETA {elapsed / frac * (1 - frac):5.0f}s"

    def _draw(self, final=False):
        frac = self.done / self.total
        elapsed = time.perf_counter() - self._start
        eta = self._eta(frac, elapsed)
        if self._tty:
            fill = int(round(frac * self.width))
            bar = "#" * fill + "-" * (self.width - fill)
            self.stream.write(f"\r{self.label} [{bar}] {100 * frac:5.1f}% {elapsed:6.1f}s{eta}")
            if final:
                self.stream.write("\n")
            self.stream.flush()
        else:
            decile = int(frac * 10)
            if decile > self._last_decile:
                self._last_decile = decile
                self.stream.write(f"{self.label} {100 * frac:5.1f}% {elapsed:6.1f}s{eta}\n")
                self.stream.flush()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.enabled:
            self.done = self.total if exc[0] is None else self.done
            self._draw(final=True)
        return False
