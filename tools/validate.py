#!/usr/bin/env python
"""Score a candidate setting on the validation frames of every shared scene, never a test frame.

    python tools/validate.py --tag default                      # the defaults, seed 0
    python tools/validate.py --tag nogate --set between_model=0 --seeds 0,1 --minutes 6
    python tools/validate.py --tag paper --recipe paper --minutes 6 --scenes traction,pushing
    python tools/validate.py --tag default --summary            # print what is there, train nothing
    python tools/validate.py --tag report --test --minutes 15 --seeds 0,1,2   # the report, once

The protocol (docs/VALIDATION.md): each run trains with ``--validation``: the validation frames
((i - 5) % 8 == 0, midway between two test frames, each with training frames on both sides, as a
test frame has) are held out of training along with the test frames, and ``endowave-cl eval``
scores the validation frames with the same function as the test frames, beside every interpolation
baseline (neighbour mean, DIS bilinear and bicubic, the in-between teacher) on the same frames.
Defaults are chosen on these figures across every scene; the test frames are read once, for the
report (``--test``: the usual split, the test frames scored; use a tag of its own).

Scenes (--scenes, comma-separated): pulling (the EndoNeRF pulling frames at --downscale 2),
traction and pushing (shared/data/endonerf_clips, 320x256), synth (a 320x256 synthetic scene of 48
frames with exact depth and flow, made once under OUT); pulling640 (the pulling frames at their full
640x512: only when --scenes names it, e.g. the report's ``--test --minutes 60 --scenes pulling640``).
Runs go to OUT/TAG/SCENE_sSEED and are kept (their checkpoints only with --keep-checkpoints): a run
with an eval.json is not trained again.  Prints per run, per scene (mean over seeds)
and the per-frame margin over the teacher against the motion between the frame's neighbours, and
writes OUT/TAG/summary.json.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
# name -> (path under shared/, --downscale)
SCENES = {
    "pulling": ("data/endonerf/pulling_soft_tissues", 2.0),
    "pulling640": ("data/endonerf/pulling_soft_tissues", 1.0),   # full size; only when named
    "traction": ("data/endonerf_clips/traction", 1.0),
    "pushing": ("data/endonerf_clips/pushing", 1.0),
    "synth": (None, 1.0),
}
SYNTH_ARGS = ["--width", "320", "--height", "256", "--frames", "48", "--seed", "3"]
MOTION_BINS = (0.0, 0.5, 1.0, 2.0, 4.0, np.inf)   # px between a frame's two neighbours


def _cli(*args) -> list:
    return [sys.executable, "-m", "endowave_cl", *map(str, args)]


def _run(cmd, log: Path) -> int:
    with open(log, "ab") as f:
        f.write(("$ " + " ".join(map(str, cmd)) + "\n").encode())
        f.flush()
        return subprocess.call(list(map(str, cmd)), stdout=f, stderr=subprocess.STDOUT, cwd=REPO)


def scene_path(name: str, shared: Path, out: Path, log: Path) -> Path:
    rel, _ = SCENES[name]
    if rel is not None:
        return shared / rel
    path = out / "synth_scene"
    if not (path / "poses_bounds.npy").is_file():
        if _run(_cli("synth", path, *SYNTH_ARGS), log) != 0:
            raise SystemExit(f"validate: error: making the synthetic scene failed (see {log})")
    return path


def train_and_eval(name: str, seed: int, a, shared: Path, base: Path) -> Path:
    run = base / f"{name}_s{seed}"
    if (run / "eval.json").is_file():
        return run
    run.mkdir(parents=True, exist_ok=True)
    log = run.parent / f"{run.name}.log"
    scene = scene_path(name, shared, base.parent, log)
    cmd = _cli("train", scene, "--out", run, *([] if a.test else ["--validation"]), "--quiet",
               "--downscale", SCENES[name][1], "--set", f"seed={seed}")
    if a.recipe:
        cmd += ["--recipe", a.recipe]
    if a.minutes:
        cmd += ["--minutes", a.minutes]
    if a.iterations:
        cmd += ["--iterations", a.iterations]
    for kv in a.set + compressed_schedule(a):
        cmd += ["--set", kv]
    t0 = time.perf_counter()
    if _run(cmd, log) != 0 or _run(_cli("eval", run, "--fps-runs", 0), log) != 0:
        raise SystemExit(f"validate: error: {name} seed {seed} failed (see {log})")
    if not a.keep_checkpoints:
        # the figures are in eval.json; a screen of many candidates otherwise fills the disk
        # (three checkpoints of 100-200 MB per run at the density cap)
        for ck in run.glob("checkpoint_*.npz"):
            ck.unlink()
    print(f"  {name} seed {seed}: trained and scored in {time.perf_counter() - t0:.0f} s", flush=True)
    return run


def compressed_schedule(a) -> list:
    """--steps N: ["iterations=N", and every schedule key (SCALED_FIELDS) of the candidate's
    configuration scaled by N over the steps it is given for], so that a short run keeps the
    schedule's shape (densification, the late phase) whatever the machine's load; [] without."""
    if not a.steps:
        return []
    sys.path.insert(0, str(REPO))
    from endowave_cl.train.config import BASE_ITERATIONS, SCALED_FIELDS, load_config
    cfg = load_config(None, dict(kv.split("=", 1) for kv in a.set), a.recipe)
    r = a.steps / float(cfg.iterations or BASE_ITERATIONS)
    keys = {f: max(1, int(round(getattr(cfg, f) * r))) for f in SCALED_FIELDS if getattr(cfg, f) > 0}
    return [f"iterations={a.steps}"] + [f"{k}={v}" for k, v in keys.items()]


def read_eval(run: Path, split: str) -> dict:
    m = json.loads((run / "eval.json").read_text())
    if m.get("split", "test") != split:
        raise SystemExit(f"validate: error: {run}/eval.json scores the {m.get('split', 'test')} frames, not the "
                         f"{split} frames (--test reads the test frames, for the final report only)")
    log = json.loads((run / "train_log.json").read_text()) if (run / "train_log.json").is_file() else {}
    m["train_seconds"] = (log.get("final") or {}).get("train_seconds", log.get("train_seconds"))
    return m


def _fmt(v, spec=".2f") -> str:
    return "n/a" if v is None else format(v, spec)


def main(argv=None) -> int:
    from endowave_cl.device import cpu_name

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tag", required=True, help="name of the candidate (its runs go to OUT/TAG)")
    ap.add_argument("--out", default="runs/validate", help="folder of the candidates' runs (default runs/validate)")
    ap.add_argument("--shared", default=str(REPO.parent / "shared"), help="the shared folder (default ../shared)")
    ap.add_argument("--scenes", default="pulling,traction,pushing,synth", help="comma-separated, of " + ", ".join(SCENES))
    ap.add_argument("--seeds", default="0", help="comma-separated seeds (default 0)")
    ap.add_argument("--recipe", help="train's --recipe")
    ap.add_argument("--minutes", type=float, help="train's --minutes (a time budget per run)")
    ap.add_argument("--iterations", type=int, help="train's --iterations (the schedule keys stay as configured)")
    ap.add_argument("--steps", type=int, help="N steps with the whole schedule compressed to them (load-independent "
                                              "screening; unlike --iterations, densification and the late phase "
                                              "keep their share)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="train's --set (repeatable)")
    ap.add_argument("--keep-checkpoints", action="store_true",
                    help="keep each run's checkpoints (default: deleted once the run is scored)")
    ap.add_argument("--summary", action="store_true", help="train nothing: summarise the runs already there")
    ap.add_argument("--test", action="store_true",
                    help="the final report: train on the usual split and score the TEST frames (read them once, "
                         "with the settings already chosen on validation figures; docs/VALIDATION.md)")
    a = ap.parse_args(argv)
    names = [s.strip() for s in a.scenes.split(",") if s.strip()]
    bad = [s for s in names if s not in SCENES]
    if bad:
        ap.error(f"--scenes: unknown {', '.join(bad)} (choose from {', '.join(SCENES)})")
    try:
        seeds = [int(s) for s in a.seeds.split(",") if s.strip()]
    except ValueError:
        ap.error(f"--seeds: expected comma-separated integers, got {a.seeds!r}")
    shared, base = Path(a.shared), Path(a.out) / a.tag
    base.mkdir(parents=True, exist_ok=True)
    print(f"validate {a.tag} ({'TEST frames: the final report' if a.test else 'validation frames'}): host {cpu_name()}, {os.cpu_count()} CPUs, load "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}; recipe {a.recipe or 'default'}, minutes "
          f"{a.minutes or '-'}, iterations {a.iterations or '-'}, steps {a.steps or '-'}, set {a.set or '-'}", flush=True)
    runs = {}
    for name in names:
        rel = SCENES[name][0]
        if rel is not None and not (shared / rel).is_dir():
            print(f"  {name}: {shared / rel} not found, skipped")
            continue
        for seed in seeds:
            run = base / f"{name}_s{seed}"
            if a.summary and not (run / "eval.json").is_file():
                continue
            runs[(name, seed)] = train_and_eval(name, seed, a, shared, base)
    # the summary covers every finished run of the candidate, also those of scenes or seeds that
    # another invocation of the same tag trained (two scenes trained side by side share summary.json)
    for name, (rel, _) in SCENES.items():
        if rel is not None and not (shared / rel).is_dir():
            continue
        for ev in sorted(base.glob(f"{name}_s*/eval.json")):
            seed = ev.parent.name[len(name) + 2:]
            if seed.isdigit():
                runs.setdefault((name, int(seed)), ev.parent)
    runs = dict(sorted(runs.items(), key=lambda kv: (list(SCENES).index(kv[0][0]), kv[0][1])))
    names = list(dict.fromkeys(name for name, _ in runs))
    if not runs:
        print("no finished runs")
        return 1
    split = "test" if a.test else "validation"
    evals = {k: read_eval(r, split) for k, r in runs.items()}
    hdr = (f"{'scene':<9} {'seed':>4} {'model':>6} {'masked':>6} {'SSIM':>6} {'LPIPS':>6} | {'teacher':>7} "
           f"{'LPIPS':>6} {'bicubic':>7} {'LPIPS':>6} | {'-teach':>6} {'-best':>6} | {'fit':>6} {'steps':>6} {'sec':>5}")
    print(f"\n{split} frames (whole-image PSNR dB unless named; -teach / -best: model minus the teacher / "
          f"the best baseline; fit: PSNR at the training frames)\n{hdr}")
    rows, summary = [], {}
    for (name, seed), m in evals.items():
        b = m["baselines"]
        r = {"scene": name, "seed": seed, "psnr": m["psnr"], "psnr_masked": m["psnr_masked"], "ssim": m["ssim"],
             "lpips": m["lpips"], "teacher": b["teacher"]["psnr"], "teacher_lpips": b["teacher"]["lpips"],
             "bicubic": b["dis_cubic"]["psnr"], "bicubic_lpips": b["dis_cubic"]["lpips"],
             "margin_teacher": m["margin_teacher"]["psnr"], "margin_best": m["margin"]["psnr"],
             "fit": (m.get("train_fit") or {}).get("psnr"), "steps": m.get("step"), "seconds": m.get("train_seconds")}
        rows.append(r)
        print(f"{name:<9} {seed:>4} {r['psnr']:6.2f} {r['psnr_masked']:6.2f} {r['ssim']:6.4f} {_fmt(r['lpips'], '6.4f')} | "
              f"{r['teacher']:7.2f} {_fmt(r['teacher_lpips'], '6.4f')} {r['bicubic']:7.2f} {_fmt(r['bicubic_lpips'], '6.4f')} | "
              f"{r['margin_teacher']:+6.2f} {r['margin_best']:+6.2f} | {_fmt(r['fit'], '6.2f')} {r['steps'] or 0:>6} "
              f"{_fmt(r['seconds'], '5.0f')}")
    print("\nper scene, mean +- std over seeds")
    for name in names:
        rs = [r for r in rows if r["scene"] == name]
        if not rs:
            continue
        agg = {k: (float(np.mean([r[k] for r in rs])), float(np.std([r[k] for r in rs])))
               for k in ("psnr", "margin_teacher", "margin_best", "lpips", "bicubic_lpips", "fit")
               if all(r[k] is not None for r in rs)}
        summary[name] = {"seeds": [r["seed"] for r in rs], **{k: v[0] for k, v in agg.items()},
                         **{k + "_std": v[1] for k, v in agg.items()}}
        txt = ", ".join(f"{k} {v[0]:.3f} +- {v[1]:.3f}" for k, v in agg.items())
        print(f"  {name} ({len(rs)} seeds): {txt}")
    # the margin over the teacher per validation frame against how far the tissue moves there
    pts = [(pf["motion"], pf["model"]["psnr"] - pf["teacher"]["psnr"]) for m in evals.values()
           for pf in m["per_frame"] if pf.get("motion") is not None and "teacher" in pf]
    if pts:
        mot, mar = np.array(pts).T
        print("\nmargin over the teacher per frame against the motion between its neighbours (all runs)")
        for lo, hi in zip(MOTION_BINS[:-1], MOTION_BINS[1:]):
            sel = (mot >= lo) & (mot < hi)
            if sel.any():
                print(f"  motion {lo:4.1f}-{hi:<4.1f} px: {int(sel.sum()):3d} frames, margin {mar[sel].mean():+.2f} dB "
                      f"(min {mar[sel].min():+.2f}, max {mar[sel].max():+.2f})")
        summary["_by_motion"] = [[float(x), float(y)] for x, y in pts]
    (base / "summary.json").write_text(json.dumps({"tag": a.tag, "runs": rows, "scenes": summary}, indent=1))
    print(f"\nwrote {base / 'summary.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
