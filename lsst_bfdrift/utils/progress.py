"""Progress on stderr for long runs (quiet when disabled): a bar for work of known
length (:class:`ProgressBar`, :class:`StageProgress`) and a running count for work
of unknown length (:class:`Activity`, e.g. an iterative fit)."""

import sys
import time

__all__ = ["ProgressBar", "StageProgress", "Activity"]


class ProgressBar:
    """Text progress bar: ``with ProgressBar(total, "label") as bar: bar(1)``.

    On a terminal the bar is redrawn in place; otherwise a line is printed at
    every 10 %, when the label changes (a new stage), and after ``every``
    seconds without a line when the work has moved (a slow stretch is not
    silent), so that logs stay short.
    ``enabled=False`` makes it silent.
    """

    def __init__(self, total, label="", *, enabled=True, stream=None, width=30, every=10.0):
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
        self.every = float(every)
        self._line_at = self._start
        self._line_done = -1
        self._line_label = None

    def __call__(self, n=1):
        self.done = min(self.done + n, self.total)
        if self.enabled:
            self._draw()

    def show(self):
        """Draw the bar now (at 0 % before any work: the label says at once what
        runs, rather than at the first tenth)."""
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
            now = time.perf_counter()
            late = now - self._line_at >= self.every and self.done != self._line_done
            relabelled = self._line_label is not None and self.label != self._line_label
            if decile > self._last_decile or late or relabelled or (final and self.failed):
                self._last_decile = max(decile, self._last_decile)
                self._line_at, self._line_done, self._line_label = now, self.done, self.label
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
        label = f"{self.label}: {stage}" if self.label else stage
        relabelled = label != self.bar.label
        self.bar.label = label
        if pos > self.bar.done:
            self.bar(pos - self.bar.done)
        elif relabelled:
            self.bar.show()  # a new stage is said when it starts

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


class Activity:
    """Progress of work whose length is not known in advance (an iterative fit):
    what runs, for how long, and how many steps it has made.

    ``with Activity("calibrate: covariance model fit", unit="model evaluations") as
    act: act()`` prints the label at the first step (work that makes no step
    says nothing), then, on a terminal, redraws ``label: 12.3 s, 1500 model
    evaluations`` at most 5 times a second, and in a log a line every
    ``every`` seconds; at the end, the time and count taken.

    Parameters
    ----------
    label : str
        What runs.
    unit : str, optional
        What a step is (plural).
    enabled : bool, optional
        False: silent.
    stream : file-like, optional
        Default ``sys.stderr``.
    every : float, optional
        Seconds between the lines of a log.
    """

    def __init__(self, label, *, unit="steps", enabled=True, stream=None, every=10.0):
        self.label = label
        self.unit = unit
        self.enabled = bool(enabled)
        self.stream = sys.stderr if stream is None else stream
        self.every = float(every)
        self.count = 0
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._start = self._last = time.perf_counter()
        self._drawn = 0

    def _write(self, text, final=False):
        if self._tty:
            self.stream.write("\r" + text.ljust(self._drawn) + ("\n" if final else ""))
            self._drawn = len(text)
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

    def __call__(self, n=1):
        """Count ``n`` steps done."""
        first = self.count == 0
        self.count += n
        if not self.enabled:
            return
        if first:
            self._write(f"{self.label} ...")
        now = time.perf_counter()
        if now - self._last >= (0.2 if self._tty else self.every):
            self._last = now
            self._write(f"{self.label}: {now - self._start:.1f} s, {self.count} {self.unit}")

    def __enter__(self):
        self._start = self._last = time.perf_counter()
        return self

    def __exit__(self, *exc):
        if self.enabled and self.count:
            end = "done" if exc[0] is None else "stopped"
            self._write(f"{self.label}: {end} in {time.perf_counter() - self._start:.1f} s "
                        f"({self.count} {self.unit})", final=True)
        return False
