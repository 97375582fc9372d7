"""A minimal progress bar for long runs (stderr; quiet when disabled)."""

import sys
import time

__all__ = ["ProgressBar", "StageProgress"]


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
        self._drawn = 0
        self.failed = False

    def __call__(self, n=1):
        self.done = min(self.done + n, self.total)
        if self.enabled:
            self._draw()

    def fail(self):
        """Mark the work as failed: on leaving the ``with`` block the bar stays
        where it stood (not 100 %) and its last line is always printed."""
        self.failed = True

    def _eta(self, frac, elapsed):
        """' ETA 12s' while running (elapsed / done x left), '' at the ends."""
        if not 0 < frac < 1 or self.failed:
            return ""
        return f" ETA {elapsed / frac * (1 - frac):5.0f}s"

    def _draw(self, final=False):
        frac = self.done / self.total
        elapsed = time.perf_counter() - self._start
        eta = self._eta(frac, elapsed)
        if self._tty:
            fill = int(round(frac * self.width))
            bar = "#" * fill + "-" * (self.width - fill)
            line = f"{self.label} [{bar}] {100 * frac:5.1f}% {elapsed:6.1f}s{eta}"
            # blanks over the end of a longer previous line (the label may change)
            self.stream.write("\r" + line.ljust(self._drawn))
            self._drawn = len(line)
            if final:
                self.stream.write("\n")
            self.stream.flush()
        else:
            decile = int(frac * 10)
            if decile > self._last_decile or (final and self.failed):
                self._last_decile = decile
                self.stream.write(f"{self.label} {100 * frac:5.1f}% {elapsed:6.1f}s{eta}\n")
                self.stream.flush()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.enabled:
            self.done = self.total if exc[0] is None and not self.failed else self.done
            self._draw(final=True)
        return False


class StageProgress:
    """Progress of one job through weighted stages, drawn as one :class:`ProgressBar`.

    ``with StageProgress({"read": 1, "maps": 8}, "a.fits") as progress:
    progress("maps", 0.5)``: the bar stands at the stages before ``maps`` plus
    half of its weight, labelled ``a.fits: maps``. The bar never goes back;
    stages not in ``weights`` (or of weight 0) are ignored, so a job may
    report stages it skips in some configurations.

    Parameters
    ----------
    weights : dict of str to float
        Stages in their order, each with its share of the time (any scale).
    label : str, optional
        Printed before the stage name.
    enabled : bool, optional
        False: silent (the job's calls still work).
    stream : file-like, optional
        Default ``sys.stderr``; a terminal gets a bar redrawn in place, a log
        a line at every 10 % (:class:`ProgressBar`).
    """

    _STEPS = 1000

    def __init__(self, weights, label="", *, enabled=True, stream=None):
        self.label = label
        self._start, self._weight = {}, {}
        pos = 0.0
        for stage, w in weights.items():
            w = float(w)
            if w > 0:
                self._start[stage], self._weight[stage] = pos, w
                pos += w
        self._total = pos if pos > 0 else 1.0
        self.bar = ProgressBar(self._STEPS, label, enabled=enabled, stream=stream)

    def __call__(self, stage, fraction=1.0):
        """Report that ``fraction`` (0 to 1) of ``stage`` is done."""
        if stage not in self._start:
            return
        f = min(max(float(fraction), 0.0), 1.0)
        pos = int(self._STEPS * (self._start[stage] + f * self._weight[stage]) / self._total)
        self.bar.label = f"{self.label}: {stage}" if self.label else stage
        if pos > self.bar.done:
            self.bar(pos - self.bar.done)

    def fail(self):
        """Mark the job as failed: the bar ends labelled ``failed`` where it
        stood, not ``done`` at 100 % (the error is the caller's to print)."""
        self.bar.fail()

    def __enter__(self):
        self.bar.__enter__()
        return self

    def __exit__(self, *exc):
        if exc[0] is None:
            end = "failed" if self.bar.failed else "done"
            self.bar.label = f"{self.label}: {end}" if self.label else end
        return self.bar.__exit__(*exc)
