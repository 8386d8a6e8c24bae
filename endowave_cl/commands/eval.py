"""Evaluate a trained run on its test frames: PSNR (masked form and whole-image form on masked
images), SSIM, LPIPS-Alex (with the [metrics] extra; else n/a) and rendering FPS (render alone,
after warm-up), beside four baselines scored the same way on the same frames: the mean of the
neighbouring training frames, a DIS optical-flow interpolation between them with bilinear and
with bicubic warps, and the in-between teacher (the target training's in-between steps fit there,
built from the training frames alone, with no model), with the model's margin over the best one
and over the teacher.  On a scene with gt_flow/ (endowave-cl synth) it also reports the
end-point error of the flow the model renders, beside DIS's on the same pixels; on a scene with
depth maps, the error of the rendered depth on the test frames' tissue (in the depth files' units
and relative to the depth).

Writes RUN/eval.json (every figure, per frame too), RUN/eval_per_frame.png (PSNR of each test
frame over time, model and baselines) and RUN/eval_worst.png (the model's worst test frame:
ground truth | render | error, mean |error| over RGB with full scale 0.25), each atomically.
eval.json is strict JSON: a non-finite figure (PSNR inf where a frame is rendered exactly, e.g. all
black) is written as null."""
from __future__ import annotations

from pathlib import Path

from ..atomic import write_json_atomic
from ..baselines import LABELS
from ..data.scene import TEST_EVERY, check_supervised
from ..errors import EndowaveError
from ..evaluation import evaluate_run, write_figures
from ..gaussians import upload
from ..run_io import load_run
from ..runtime import get_runtime


MAX_FPS_RUNS = 10000   # timed renders for the FPS figure


def add_arguments(p) -> None:
    p.add_argument("run", help="run folder written by endowave-cl train")
    p.add_argument("--scene", help="scene folder (default: the one the run was trained on)")
    p.add_argument("--fps-runs", type=int, default=10,
                   help="timed renders for the FPS figure, >= 0 (default 10; 0: skip, fps is null in eval.json)")
    p.add_argument("--no-baselines", action="store_true",
                   help="skip the interpolation baselines (neighbour mean, DIS with bilinear and bicubic warps, in-between teacher)")


def _lp(v) -> str:
    return "n/a" if v is None else f"{v:.4f}"


def table(m: dict) -> str:
    """The printed comparison: one line per renderer, then the margin and, with gt_flow, the flow."""
    lines = [f"{'on the ' + m.get('split', 'test') + ' frames':<38} {'PSNR':>7} {'masked':>7} {'SSIM':>7} {'LPIPS':>7}"]
    entries = [("model", m)] + [(LABELS[n], b) for n, b in m.get("baselines", {}).items()]
    for label, e in entries:
        lines.append(f"{label:<38} {e['psnr']:7.2f} {e['psnr_masked']:7.2f} {e['ssim']:7.4f} {_lp(e['lpips']):>7}")
    mg = m.get("margin")
    if mg is not None:
        lp = "" if mg["lpips"] is None else f", LPIPS {mg['lpips']:+.4f}"
        lines.append(f"margin over the {LABELS[mg['over']]}: {mg['psnr']:+.2f} dB (masked {mg['psnr_masked']:+.2f} "
                     f"dB), SSIM {mg['ssim']:+.4f}{lp}  (positive = the model is better)")
    mt = m.get("margin_teacher")
    if mt is not None and mg is not None and mg["over"] != "teacher":
        lp = "" if mt["lpips"] is None else f", LPIPS {mt['lpips']:+.4f}"
        lines.append(f"margin over the {LABELS['teacher']}: {mt['psnr']:+.2f} dB (masked {mt['psnr_masked']:+.2f} "
                     f"dB), SSIM {mt['ssim']:+.4f}{lp}")
    fl = m.get("flow")
    if fl is not None:
        lines.append(f"flow to the next frame vs gt_flow ({fl['frames']} test frames, {fl['pixels']} tissue pixels): "
                     f"end-point error model {fl['model_epe']:.3f} px, DIS on the two frames "
                     f"{fl['dis_epe']:.3f} px, zero flow {fl['gt_magnitude']:.3f} px; "
                     f"mean magnitude model {fl['model_magnitude']:.3f} px, true {fl['gt_magnitude']:.3f} px")
    dp = m.get("depth")
    if dp is not None:
        lines.append(f"depth vs the depth maps ({dp['frames']} test frames, {dp['pixels']} tissue pixels): mean "
                     f"absolute error {dp['mae']:.4g} (the depth files' units), {100 * dp['relative']:.2f}% of the depth")
    tf = m.get("train_fit")
    if tf is not None:
        lines.append(f"model at its {tf['frames']} training frames: PSNR {tf['psnr']:.2f} dB (masked {tf['psnr_masked']:.2f} dB)")
    lp_note = "" if m["lpips"] is not None else "  (LPIPS n/a: install the [metrics] extra)"
    lines.append("PSNR: whole image of masked images; masked: tissue pixels only; LPIPS-Alex" + lp_note)
    return "\n".join(lines)


def run(args) -> int:
    if args.fps_runs < 0:
        raise EndowaveError(f"--fps-runs must be >= 0, got {args.fps_runs}")
    if args.fps_runs > MAX_FPS_RUNS:    # 1e20 timed renders never end (issue 57)
        raise EndowaveError(f"--fps-runs must be at most {MAX_FPS_RUNS}, got {args.fps_runs}")
    r = load_run(args.run, args.scene)
    if not r.scene.test_indices:
        n = len(r.scene.frames)
        raise EndowaveError(f"{r.scene.path}: {n} frame(s) and no test frame to evaluate (test frames are "
                            f"1, {1 + TEST_EVERY}, {1 + 2 * TEST_EVERY}, ...: eval needs at least 2 frames)")
    check_supervised(r.scene, r.scene.split)   # a frame whose mask is all tool cannot be scored (issue 57)
    rt = get_runtime(getattr(args, "device", None))
    params = upload(rt, r.gaussians)
    m = evaluate_run(rt, params, r.scene, args.fps_runs, with_baselines=not args.no_baselines, with_train_fit=True)
    m.update({"step": r.step, "gaussians": len(r.gaussians), "checkpoint": str(r.checkpoint),
              "scene": str(r.scene.path), "size": [r.scene.width, r.scene.height]})
    title = (f"{Path(r.scene.path).name} {r.scene.width}x{r.scene.height}, step {r.step}, "
             f"{len(r.gaussians)} Gaussians")
    m.update(write_figures(args.run, rt, params, r.scene, m, title))
    fps = "n/a" if m["fps"] is None else f"{m['fps']:.1f}"
    print(f"{m['test_frames']} {m['split']} frames of {title}; render FPS {fps} on {rt.name}")
    print(table(m))
    path = Path(args.run) / "eval.json"
    write_json_atomic(path, m)      # strict JSON: PSNR inf (a frame rendered exactly) and NaN become null
    print(f"wrote {path}, {m['per_frame_plot']}, {m['worst_frame_image']} (worst test frame {m['worst_frame']})")
    curves = [Path(args.run) / n for n in ("train_curves.png", "train_curves.csv", "tensorboard")]
    if any(p.exists() for p in curves):        # written by train (train/curves.py)
        print("training curves: " + ", ".join(str(p) for p in curves if p.exists()))
    return 0
