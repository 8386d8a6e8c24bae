"""The dataset-level report: ROOT/report.md, report.json and report.csv, one row per scene and the
mean over the scenes that finished, read from the run folders' own files (eval.json,
train_log.json, RUN/batch/ records), so a re-run that does no work writes the same report.

Columns: PSNR in both forms (whole image of masked images; tissue pixels only), SSIM, LPIPS-Alex,
the same four for the interpolation baselines of ``endowave-cl eval`` (neighbour mean, DIS flow
interpolation with bilinear and with bicubic warps) and the model's margin over the best one, Gaussians, training steps and seconds,
the device, the render FPS, the training attempts, and the error of a scene that failed.
"""
from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Dict, List, Optional

from ..atomic import write_bytes_atomic, write_json_atomic
from . import tasks as T

METRICS = ("psnr", "psnr_masked", "ssim", "lpips")
BASELINES = ("mean", "dis", "dis_cubic", "teacher")   # endowave_cl.baselines.NAMES
# numeric columns, in order; the mean row averages them
NUMERIC = (list(METRICS) + [f"{b}_{k}" for b in BASELINES for k in METRICS]
           + ["margin_psnr", "margin_psnr_masked", "margin_ssim", "margin_lpips",
              "margin_teacher_psnr", "margin_teacher_lpips", "gaussians", "steps", "train_seconds", "fps",
              "test_frames"])
COLUMNS = ["scene", "status"] + NUMERIC + ["margin_over", "device", "attempts", "error", "run"]


def _num(v):
    return v if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def scene_row(manifest, scene, tasks: Optional[dict] = None) -> dict:
    """One scene's row.  status: "done" (every stage of the manifest complete), "failed" (a stage
    failed; "error" holds its one-line message), or "incomplete" (interrupted, or not run)."""
    run = manifest.root / scene.name
    row: Dict[str, object] = {c: None for c in COLUMNS}
    row.update(scene=scene.name, run=scene.name)
    errors, complete = [], True
    for stage in manifest.stages:
        t = (tasks or {}).get((scene.name, stage))
        state = t.state if t is not None else T.stage_status(manifest, scene, stage, run)[0]
        if state in ("error", "failed"):
            errors.append(t.why if t is not None and t.why else f"{stage} failed")
        elif state not in ("done", "ok"):
            complete = False
    if not errors and tasks is None:
        for stage in manifest.stages:          # no task list: recorded failures count too
            f = T.read_json(T.record(run, stage, ".failed"))
            if isinstance(f, dict):
                errors.append(str(f.get("error") or f"{stage} failed"))
    row["status"] = "failed" if errors else ("done" if complete else "incomplete")
    row["error"] = "; ".join(errors) or None
    final = T.train_final(run)
    if final is not None:
        row.update(steps=_num(final.get("step")), gaussians=_num(final.get("gaussians")),
                   train_seconds=_num(final.get("train_seconds")))
    att = T.read_json(T.record(run, "train", ".attempt"))
    if isinstance(att, dict):
        row["attempts"] = _num(att.get("attempt"))
    ev = T.read_json(run / "eval.json") if "eval" in manifest.stages else None
    ev_rec = T.read_json(T.record(run, "eval"))
    if isinstance(ev, dict) and (not isinstance(ev_rec, dict) or ev_rec.get("model") == T.model_token(run)):
        for k in METRICS:
            row[k] = _num(ev.get(k))
        for b in BASELINES:
            bl = (ev.get("baselines") or {}).get(b) or {}
            for k in METRICS:
                row[f"{b}_{k}"] = _num(bl.get(k))
        mg = ev.get("margin") or {}
        for k in METRICS:
            row[f"margin_{k}"] = _num(mg.get(k))
        row["margin_over"] = mg.get("over")
        mt = ev.get("margin_teacher") or {}
        row["margin_teacher_psnr"], row["margin_teacher_lpips"] = _num(mt.get("psnr")), _num(mt.get("lpips"))
        row["device"] = ev.get("device")
        row["fps"] = _num(ev.get("fps"))
        row["test_frames"] = _num(ev.get("test_frames"))
        row["gaussians"] = _num(ev.get("gaussians")) if ev.get("gaussians") is not None else row["gaussians"]
    return row


def mean_row(rows: List[dict]) -> dict:
    """The mean of each numeric column over the finished scenes (None when one of them lacks it:
    a mean over a different set of scenes would not compare)."""
    done = [r for r in rows if r["status"] == "done"]
    out: Dict[str, object] = {c: None for c in COLUMNS}
    out.update(scene=f"mean ({len(done)} scene{'s' if len(done) != 1 else ''})", status="mean")
    for c in NUMERIC:
        vals = [r[c] for r in done]
        if vals and all(v is not None for v in vals):
            out[c] = sum(vals) / len(vals)
    return out


def std_row(rows: List[dict]) -> dict:
    """The sample standard deviation of each numeric column over the finished scenes (seeds, when
    the manifest repeats a scene with other seeds); None with fewer than two."""
    done = [r for r in rows if r["status"] == "done"]
    out: Dict[str, object] = {c: None for c in COLUMNS}
    out.update(scene=f"std ({len(done)} scene{'s' if len(done) != 1 else ''})", status="std")
    for c in NUMERIC:
        vals = [r[c] for r in done]
        if len(vals) >= 2 and all(v is not None for v in vals):
            mu = sum(vals) / len(vals)
            out[c] = (sum((v - mu) ** 2 for v in vals) / (len(vals) - 1)) ** 0.5
    return out


def build_report(manifest, tasks: Optional[dict] = None) -> dict:
    rows = [scene_row(manifest, s, tasks) for s in manifest.scenes]
    counts = {k: sum(r["status"] == k for r in rows) for k in ("done", "failed", "incomplete")}
    return {"manifest": str(manifest.path), "root": str(manifest.root), "stages": list(manifest.stages),
            "counts": counts, "columns": COLUMNS, "scenes": rows, "mean": mean_row(rows), "std": std_row(rows)}


def _f(v, fmt: str) -> str:
    return "n/a" if v is None else format(v, fmt)


BASELINE_LABELS = {"mean": "neighbour mean", "dis": "DIS interp.", "dis_cubic": "DIS bicubic",
                   "teacher": "teacher"}


def markdown(rep: dict) -> str:
    shown = [b for b in BASELINES if any(r.get(f"{b}_psnr") is not None for r in rep["scenes"])]
    head = (["scene", "PSNR", "PSNR masked", "SSIM", "LPIPS"] + [f"{BASELINE_LABELS[b]} PSNR" for b in shown]
            + ["margin dB (over)", "test frames", "Gaussians", "steps", "train time", "FPS", "device"])
    lines = ["# endowave-cl batch report", "",
             f"Manifest `{rep['manifest']}`; stages {', '.join(rep['stages'])}; "
             f"{rep['counts']['done']} scene(s) done, {rep['counts']['failed']} failed, "
             f"{rep['counts']['incomplete']} incomplete.", "",
             "| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 2) + "---|"]
    std = rep.get("std") or {}

    def cell(r, key, fmt, with_std=False):
        v = _f(r[key], fmt)
        if with_std and std.get(key) is not None and r[key] is not None:
            v += f" +- {std[key]:.2f}"
        return v

    def line(r, bold=False):
        name = f"**{r['scene']}**" if bold else r["scene"]
        if r["status"] == "failed":
            return f"| {name} | failed |" + " |" * (len(head) - 2)
        gauss = "n/a" if r["gaussians"] is None else f"{r['gaussians']:.0f}"
        steps = "n/a" if r["steps"] is None else f"{r['steps']:.0f}"
        frames = "n/a" if r["test_frames"] is None else f"{r['test_frames']:.0f}"
        over = BASELINE_LABELS.get(r["margin_over"], r["margin_over"]) if r["margin_over"] else None
        margin = cell(r, "margin_psnr", "+.2f", bold) + (f" ({over})" if over else "")
        cells = ([name, cell(r, "psnr", ".2f", bold), cell(r, "psnr_masked", ".2f", bold),
                  _f(r["ssim"], ".4f"), _f(r["lpips"], ".4f")]
                 + [cell(r, f"{b}_psnr", ".2f", bold) for b in shown]
                 + [margin, frames, gauss, steps, f"{_f(r['train_seconds'], '.0f')} s", _f(r["fps"], ".1f"),
                    r["device"] or ("" if bold else "n/a")])
        return "| " + " | ".join(cells) + " |"
    lines += [line(r) for r in rep["scenes"]]
    lines.append(line(rep["mean"], bold=True))
    failed = [r for r in rep["scenes"] if r["status"] != "done"]
    if failed:
        lines += ["", "## Not done", ""]
        lines += [f"- {r['scene']}: {r['status']}" + (f": {r['error']}" if r["error"] else "") for r in failed]
    lines += ["", "PSNR: whole image of masked images; PSNR masked: tissue pixels only; LPIPS-Alex (n/a without "
              "the [metrics] extra). Baselines (from `endowave-cl eval`, scored on the same test frames): the "
              "mean of the neighbouring training frames, DIS optical-flow interpolation between them with "
              "bilinear and with bicubic warps, and the in-between teacher where eval scored it; margin: the "
              "model minus the best of them by whole-image PSNR, named in brackets (positive = the model is "
              "better). The mean row is over the scenes that are done, with +- the standard deviation over "
              "them where there are several (over seeds when the scenes are one scene with several seeds). "
              "Every figure per scene, the baselines' SSIM and LPIPS included, is in report.json and "
              "report.csv (with a std row).", ""]
    return "\n".join(lines)


def csv_text(rep: dict) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    w.writeheader()
    for r in rep["scenes"] + [rep["mean"]] + ([rep["std"]] if rep.get("std") else []):
        w.writerow({k: ("" if v is None else v) for k, v in r.items()})
    return buf.getvalue()


def write_report(manifest, tasks: Optional[dict] = None) -> dict:
    """Write ROOT/report.json, report.md and report.csv (each atomically); returns the report."""
    rep = build_report(manifest, tasks)
    root = Path(manifest.root)
    write_json_atomic(root / "report.json", rep)
    write_bytes_atomic(root / "report.md", markdown(rep).encode())
    write_bytes_atomic(root / "report.csv", csv_text(rep).encode())
    return rep
