"""Cold start (issue 58): no rate or time left while the first steps build kernels, the rate measured
from the steps after them, build time counted apart (Runtime.timed_build, Trainer._split_build_time)."""
from __future__ import annotations

import io

from endowave_cl import progress as PR


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_plain_progress_holds_then_measures_from_restart():
    out, clock = io.StringIO(), Clock()
    bar = PR.PlainProgress(total=100, desc="train", file=out, interval=1.0, clock=clock)
    PR.hold_rate(bar)
    clock.t += 70.0             # the first step builds kernels for 70 s
    bar.update(1)
    for _ in range(4):
        clock.t += 0.1
        bar.update(1)
    assert "measuring the rate" in out.getvalue() and "left" not in out.getvalue()
    PR.restart_rate(bar)
    for _ in range(20):
        clock.t += 0.1          # 10 it/s from here on
        bar.update(1)
    line = out.getvalue().splitlines()[-1]
    assert "10 it/s" in line and "8s left" in line, line
    bar.close()
    assert "in all" in out.getvalue().splitlines()[-1] and "1m12s in all" in out.getvalue(), out.getvalue()


def test_tqdm_bar_holds_then_restarts():
    from tqdm import tqdm
    out = io.StringIO()
    bar = tqdm(total=50, file=out, mininterval=0, desc="train")
    PR.hold_rate(bar)
    bar.update(3)
    assert "measuring the rate" in out.getvalue()
    PR.restart_rate(bar)
    bar.update(2)
    assert bar.n == 5 and bar.initial == 3 and bar.bar_format is None
    bar.close()


def test_timed_build_counts_and_notifies_once():
    from endowave_cl.runtime import Runtime
    rt = Runtime.__new__(Runtime)      # only the build bookkeeping, no device
    rt.build_seconds, seen = 0.0, []
    rt.build_notice = seen.append
    with rt.timed_build("a.cl"):
        pass
    with rt.timed_build("b.cl"):
        pass
    assert seen == ["a.cl"] and rt.build_seconds >= 0.0


def test_split_build_time():
    from endowave_cl.train.trainer import ETA_WARMUP_STEPS, Trainer
    tr = Trainer.__new__(Trainer)
    tr._build0 = 0.0

    class RT:
        build_seconds = 3.0            # 1 s before the loop, 2 s after the warm-up steps
    tr.rt = RT()
    times = [60.0] + [0.1] * (ETA_WARMUP_STEPS - 1) + [0.1] * 100
    loop = sum(times) + 2.0
    train, build = tr._split_build_time(loop, times, loop_build0=1.0, warm_build=1.0)
    assert abs(train - 0.1 * (len(times))) < 1e-6
    assert abs(build - (1.0 + 59.9 + 2.0)) < 1e-6
