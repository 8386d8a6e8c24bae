"""Progress output: plain lines every few seconds when stdout is not a terminal, tqdm on one."""
from __future__ import annotations

import io

from endowave_cl import progress as PR


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_plain_lines_every_interval_and_at_the_end():
    out, clock = io.StringIO(), Clock()
    bar = PR.PlainProgress(total=100, desc="train", unit="it", file=out, interval=5.0, clock=clock)
    for i in range(100):
        clock.t += 0.5          # 2 it/s: a line every 10 steps
        bar.update(1)
        if i == 40:
            bar.set_postfix(loss="0.0412", psnr="27.31")
            bar.write("step 40: test PSNR 27.0 dB")
    bar.close()
    text = out.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    progress_lines = [ln for ln in lines if ln.startswith("train: ")]
    assert len(progress_lines) == 100 // 10 + 1            # one per 5 s, one at the end
    assert progress_lines[0] == "train: 10/100 it (10%), 2 it/s, 45s left"
    assert progress_lines[-1].startswith("train: 100/100 it (100%), 2 it/s, 50s in all, loss=0.0412 psnr=27.31")
    assert "step 40: test PSNR 27.0 dB" in lines


def test_plain_iteration_resume_and_disable():
    out, clock = io.StringIO(), Clock()
    seen = []
    for x in PR.PlainProgress(range(3), desc="render", unit="frame", file=out, interval=1e9, clock=clock):
        clock.t += 1.0
        seen.append(x)
    assert seen == [0, 1, 2]
    assert out.getvalue() == "render: 3/3 frame (100%), 1 frame/s, 3s in all\n"
    out2 = io.StringIO()
    bar = PR.PlainProgress(total=10, initial=4, file=out2, disable=True, interval=0.0, clock=clock)
    bar.update(3)
    bar.close()
    assert out2.getvalue() == ""
    assert bar.n == 7


def test_mode_follows_stdout_and_env(monkeypatch):
    class Tty(io.StringIO):
        def isatty(self):
            return True
    monkeypatch.delenv(PR.ENV_MODE, raising=False)
    monkeypatch.setattr("sys.stdout", io.StringIO())
    assert isinstance(PR.progress(range(2)), PR.PlainProgress)
    monkeypatch.setattr("sys.stdout", Tty())
    assert not isinstance(PR.progress(range(2), dynamic_ncols=True), PR.PlainProgress)
    monkeypatch.setenv(PR.ENV_MODE, "plain")
    assert isinstance(PR.progress(range(2)), PR.PlainProgress)
    monkeypatch.setenv(PR.ENV_MODE, "off")
    assert PR.progress(range(2)).disable
