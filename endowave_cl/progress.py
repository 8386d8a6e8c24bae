"""Progress display: a tqdm bar on a terminal, plain lines elsewhere.

A tqdm bar redraws itself with carriage returns, which in a CI log, a nohup file or a pipe becomes
one huge line (or thousands).  When stdout is not a terminal, ``progress`` returns a ``PlainProgress``
instead: one line every ``interval`` seconds (and one at the end) with the count, rate, time left and
the last postfix, e.g. ``train: 300/1500 it (20%), 11.2 it/s, 1m47s left, loss=0.0412 psnr=27.31``.

$ENDOWAVE_PROGRESS = bar | plain | off overrides the choice; $ENDOWAVE_PROGRESS_INTERVAL sets the
seconds between plain lines (default 5).
"""
from __future__ import annotations

import sys
import time
from typing import Iterable, Optional

from tqdm import tqdm

from . import env      # every ENDOWAVE_* variable is parsed there, with a named error

ENV_MODE = "ENDOWAVE_PROGRESS"
ENV_INTERVAL = "ENDOWAVE_PROGRESS_INTERVAL"
DEFAULT_INTERVAL = 5.0


def _fmt_time(s: float) -> str:
    s = int(round(s))
    if s >= 3600:
        return f"{s // 3600}h{s % 3600 // 60:02d}m"
    if s >= 60:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s}s"


class PlainProgress:
    """The part of tqdm's interface endowave-cl uses (update, set_postfix, write, close, iteration,
    with), printing plain lines to ``file`` at most every ``interval`` seconds."""

    def __init__(self, iterable: Optional[Iterable] = None, total: Optional[int] = None, initial: int = 0,
                 desc: str = "", unit: str = "it", disable: bool = False, file=None,
                 interval: Optional[float] = None, clock=time.monotonic):
        self.iterable = iterable
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)
        self.total, self.n, self.initial = total, int(initial), int(initial)
        self.desc, self.unit, self.disable = desc, unit, disable
        self.file = file
        self.interval = float(interval if interval is not None else
                              env.get(ENV_INTERVAL) or DEFAULT_INTERVAL)
        self.clock = clock
        self.t0 = self.last = self.t_begin = clock()
        self.postfix = ""
        self.closed = False
        self.hold = False     # hold_rate(): no rate or time left yet

    def _out(self):
        return self.file if self.file is not None else sys.stdout

    def _line(self) -> str:
        dt = max(self.clock() - self.t0, 1e-9)
        done = self.n - self.initial
        rate = done / dt
        s = f"{self.desc}: {self.n}" if self.desc else f"{self.n}"
        if self.total:
            s += f"/{self.total} {self.unit} ({100.0 * self.n / self.total:.0f}%)"
        else:
            s += f" {self.unit}"
        if self.hold and not self.closed:
            s += ", measuring the rate"
            done = 0
        s += f", {rate:.3g} {self.unit}/s" if done else ""
        if self.total and done and self.n < self.total:
            s += f", {_fmt_time((self.total - self.n) / rate)} left"
        if self.closed:
            s += f", {_fmt_time(self.clock() - self.t_begin)} in all"
        return s + (f", {self.postfix}" if self.postfix else "")

    def _emit(self) -> None:
        f = self._out()
        f.write(self._line() + "\n")
        f.flush()
        self.last = self.clock()

    def update(self, n: int = 1) -> None:
        self.n += n
        if not self.disable and self.clock() - self.last >= self.interval:
            self._emit()

    def set_postfix(self, **kw) -> None:
        self.postfix = " ".join(f"{k}={v}" for k, v in kw.items())

    def write(self, s: str) -> None:
        f = self._out()
        f.write(s + "\n")
        f.flush()

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        if not self.disable:
            self._emit()

    def __iter__(self):
        for x in self.iterable:
            yield x
            self.update(1)
        self.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


HOLD_FORMAT = "{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}, measuring the rate{postfix}]"


def hold_rate(bar) -> None:
    """Show no rate or time left until restart_rate(bar) (a tqdm bar or a PlainProgress)."""
    if getattr(bar, "disable", False):
        return
    if isinstance(bar, PlainProgress):
        bar.hold = True
    else:
        bar.bar_format = HOLD_FORMAT
        bar.refresh()


def restart_rate(bar) -> None:
    """Measure the rate and time left from now on (a tqdm bar or a PlainProgress): the first steps
    of a run build kernels and fill caches, and a rate that counts them predicts hours for minutes."""
    if getattr(bar, "disable", False):
        return
    if isinstance(bar, PlainProgress):
        bar.t0, bar.initial, bar.hold = bar.clock(), bar.n, False
        return
    bar.bar_format = None
    n, postfix = bar.n, getattr(bar, "postfix", None)
    bar.reset(total=bar.total)       # start time and tqdm's smoothed rates start over
    bar.initial = bar.n = bar.last_print_n = n
    if postfix:
        bar.postfix = postfix
    bar.refresh()


def plain_wanted() -> bool:
    mode = env.get(ENV_MODE)
    if mode in ("plain", "bar"):
        return mode == "plain"
    try:
        return not sys.stdout.isatty()
    except (AttributeError, ValueError):   # replaced or closed stdout
        return True


def progress(iterable: Optional[Iterable] = None, total: Optional[int] = None, initial: int = 0,
             desc: str = "", unit: str = "it", disable: bool = False, **tqdm_kw):
    """A tqdm bar when stdout is a terminal, else a PlainProgress; the same calls work on both.
    tqdm_kw (dynamic_ncols, ...) go to tqdm only."""
    if env.get(ENV_MODE) == "off":
        disable = True
    if plain_wanted():
        return PlainProgress(iterable, total=total, initial=initial, desc=desc, unit=unit, disable=disable)
    return tqdm(iterable, total=total, initial=initial, desc=desc, unit=unit, disable=disable, **tqdm_kw)
