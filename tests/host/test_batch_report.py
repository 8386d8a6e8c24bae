"""batch report.md and progress (issue 58): every baseline the margin may be taken over is shown and
the margin names it, +- std over the finished scenes, test-frame counts, FPS; queued apart from
running.  No cluster: the report is built from rows, the progress line from a runner's task table."""
from __future__ import annotations

import time
from types import SimpleNamespace

from endowave_cl.batch import report as R


def _row(name, psnr, dis, cubic, fps):
    r = {c: None for c in R.COLUMNS}
    best = max(dis, cubic)
    r.update(scene=name, status="done", run=name, psnr=psnr, psnr_masked=psnr, ssim=0.9, lpips=None,
             mean_psnr=30.0, dis_psnr=dis, dis_cubic_psnr=cubic, margin_psnr=psnr - best,
             margin_over="dis_cubic" if cubic >= dis else "dis", test_frames=8, gaussians=1000, steps=100,
             train_seconds=60.0, fps=fps, device="dev")
    return r


def test_markdown_shows_the_baseline_of_the_margin_std_frames_and_fps():
    rows = [_row("a", 31.70, 34.75, 34.50, 12.5), _row("b", 33.0, 33.0, 33.5, 10.0)]
    rep = {"manifest": "m.toml", "root": "/r", "stages": ["train", "eval"],
           "counts": {"done": 2, "failed": 0, "incomplete": 0}, "columns": R.COLUMNS, "scenes": rows,
           "mean": R.mean_row(rows), "std": R.std_row(rows)}
    md = R.markdown(rep)
    header = next(ln for ln in md.splitlines() if ln.startswith("| scene"))
    assert "DIS interp. PSNR" in header and "DIS bicubic PSNR" in header and "neighbour mean PSNR" in header
    assert "test frames" in header and "FPS" in header
    row_a = next(ln for ln in md.splitlines() if ln.startswith("| a |"))
    assert "-3.05 (DIS interp.)" in row_a and "34.75" in row_a and "| 8 |" in row_a and "12.5" in row_a
    row_b = next(ln for ln in md.splitlines() if ln.startswith("| b |"))
    assert "-0.50 (DIS bicubic)" in row_b
    mean = next(ln for ln in md.splitlines() if ln.startswith("| **mean (2 scenes)**"))
    assert "32.35 +- 0.92" in mean, mean
    assert R.std_row(rows[:1])["psnr"] is None        # one scene: no spread
    assert R.csv_text(rep).splitlines()[-1].startswith("std (2 scenes),std,")


def test_progress_counts_queued_apart_from_running(monkeypatch):
    from endowave_cl.batch import runner as RN
    tasks = {("a", "train"): RN.Task("a", "train", "running", ""), ("b", "train"): RN.Task("b", "train", "running", ""),
             ("c", "train"): RN.Task("c", "train", "todo", "")}
    fake = SimpleNamespace(tasks=tasks, _started=lambda t: t.scene == "a")
    line = RN.Runner._overall_line(fake, time.time())
    assert "1 running, 1 queued, 1 waiting" in line, line
