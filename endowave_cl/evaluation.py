"""Evaluation of a model on a scene's test frames, the way papers report it (DESIGN.md), beside the
baselines a user would reach for without a 4D model (baselines.py), and the figures that show where
it stands: PSNR per frame over time and the worst test frame."""
from __future__ import annotations

import io
import statistics
import time
from pathlib import Path
from typing import Dict

import cv2
import numpy as np

from .atomic import write_bytes_atomic, write_png_atomic
from .baselines import LABELS, NAMES, baseline_scores, summarise
from .data.flow import _fit_to_scene, estimate_flow, valid_mask
from .errors import DataError
from .lpips import lpips_available
from .metrics import frame_scores, psnr, psnr_masked
from .render import render

# The error panel of the worst-frame image maps mean |render - ground truth| over RGB linearly onto
# the colour map, saturating at this value (fixed, so that images of different runs compare).
ERROR_FULL_SCALE = 0.25

# (scene path, width, height, test frames) -> {k: (gt flow [H, W, 2], valid [H, W] bool, dis epe)}
_FLOW_CACHE: Dict[tuple, dict] = {}


def evaluate_run(rt, params, scene, fps_runs: int = 10, with_lpips: bool = True,
                 with_baselines: bool = False, with_train_fit: bool = False) -> dict:
    """Test-frame metrics of device parameters: PSNR (masked form and whole-image form on masked
    images), SSIM, LPIPS-Alex (None when unavailable or not asked for) and render FPS (median of
    fps_runs renders after warm-up; None when fps_runs is 0), plus "per_frame" (each test frame's
    index, name, time and figures).

    When the test frames have depth maps, "depth" holds the mean absolute error of the rendered
    depth (divided by the accumulated alpha: the expected depth of what is seen) over their valid
    tissue pixels, in the units of the scene's depth files ("mae") and relative to the mean true
    depth there ("relative"); else None.

    When the scene has gt_flow/ (synthetic scenes), "flow" holds the end-point error of the flow
    the model renders from each test frame to the next frame against the ground truth, beside
    DIS's error on the same pixels (see ``flow_references``); else "flow" is None.

    with_baselines: also score the interpolation baselines (the neighbour mean, the DIS flow
    interpolation with bilinear and bicubic warps, and the in-between teacher: baselines.py;
    computed once per scene and process) on the same frames with the same function and add
    "baselines" {name: means}, "margin" (model minus the best baseline by whole-image PSNR:
    psnr, psnr_masked and ssim as model - baseline, lpips as baseline - model, so positive = the
    model is better everywhere), "margin_teacher" (the same over the teacher) and each baseline's
    figures in "per_frame", with "motion": the mean flow magnitude (px) between the frame's two
    neighbours, where they are a training pair.  Off by default: the trainer's periodic evaluation
    calls this without it.

    with_train_fit: also "train_fit", the mean whole-image PSNR and masked PSNR of the model at
    its training frames (how closely it fits what it saw, beside what it shows in between)."""
    if not (isinstance(fps_runs, int) and fps_runs >= 0):
        raise ValueError(f"evaluate_run: fps_runs must be an integer >= 0 (0: no FPS), got {fps_runs!r}")
    use_lpips = bool(with_lpips and lpips_available())
    flow_refs = flow_references(scene)
    rows = []
    for k in scene.test_indices:
        f = scene.frames[k]
        t_flow = scene.frames[k + 1].time if k in flow_refs else None
        out = render(rt, params, f.camera, f.time, t_flow, select=True).host()   # the same images, faster
        row = {"index": k, "name": f.name, "time": f.time,
               "model": frame_scores(out["image"], f.image, f.mask, use_lpips)}
        if k in flow_refs:
            row["flow"] = _flow_row(out["flow"], flow_refs[k])
        if f.depth is not None:
            row["depth"] = _depth_row(out["depth"], out["alpha"], f)
        rows.append(row)
    m = _means(rows, "model")
    fps = None
    if fps_runs > 0:
        fps = _render_fps(rt, params, scene.frames[scene.test_indices[0]], fps_runs)
    m.update({"fps": fps, "test_frames": len(scene.test_indices), "device": rt.name,
              "split": getattr(scene, "split", "test")})
    m["flow"] = _flow_summary(rows) if flow_refs else None
    m["depth"] = _depth_summary(rows, scene.world_scale)
    if with_baselines:
        base = baseline_scores(scene, use_lpips)
        for row, b in zip(rows, base):
            row.update({"neighbours": b["neighbours"], "fraction": b["fraction"], "motion": b.get("motion")})
            row.update({name: b[name] for name in NAMES})
        m["baselines"] = {name: summarise(base, name) for name in NAMES}
        m["margin"] = margin(m, m["baselines"])
        m["margin_teacher"] = margin(m, {"teacher": m["baselines"]["teacher"]})
    if with_train_fit:
        m["train_fit"] = train_fit(rt, params, scene)
    m["per_frame"] = rows
    return m


def train_fit(rt, params, scene) -> dict:
    """{"psnr", "psnr_masked", "frames"}: the model's mean whole-image and masked PSNR at the
    scene's training frames."""
    vals, masked = [], []
    for k in scene.train_indices:
        f = scene.frames[k]
        img = np.clip(render(rt, params, f.camera, f.time, select=True).host()["image"], 0, 1)
        m = np.ones(f.image.shape[:2], np.float32) if f.mask is None else f.mask
        vals.append(psnr(img * m[..., None], f.image * m[..., None]))
        masked.append(psnr_masked(img, f.image, m))
    return {"psnr": float(np.mean(vals)), "psnr_masked": float(np.mean(masked)), "frames": len(vals)}


def margin(model: dict, baselines: dict) -> dict:
    """The model's margin over the better baseline (by whole-image PSNR); positive = model better."""
    best = max(baselines, key=lambda name: baselines[name]["psnr"])
    b = baselines[best]
    out = {"over": best}
    for key in ("psnr", "psnr_masked", "ssim"):
        out[key] = float(model[key] - b[key])
    out["lpips"] = None if model["lpips"] is None or b["lpips"] is None else float(b["lpips"] - model["lpips"])
    return out


def _means(rows, name) -> dict:
    out = {}
    for key in ("psnr", "psnr_masked", "ssim", "lpips"):
        vals = [r[name][key] for r in rows]
        out[key] = None if any(v is None for v in vals) else float(np.mean(vals))
    return out


# ------------------------------------------------------------------------------ depth vs depth maps
def _depth_row(depth, alpha, frame) -> dict:
    """Sums over one test frame's valid tissue pixels (scene units): |error| and true depth."""
    pred = depth / np.maximum(alpha, 1e-6)                     # [H, W]
    valid = frame.depth > 0
    if frame.mask is not None:
        valid &= frame.mask > 0.5
    err = np.abs(pred - frame.depth)[valid]
    return {"abs_sum": float(err.sum(dtype=np.float64)), "true_sum": float(frame.depth[valid].sum(dtype=np.float64)),
            "pixels": int(valid.sum())}


def _depth_summary(rows, world_scale: float):
    d = [r["depth"] for r in rows if "depth" in r]
    n = sum(x["pixels"] for x in d)
    if not d or n == 0:
        return None
    mae = sum(x["abs_sum"] for x in d) / n                     # scene units
    return {"mae": mae / world_scale, "relative": mae / max(sum(x["true_sum"] for x in d) / n, 1e-12),
            "frames": len(d), "pixels": n}



def depth_figures(rt, params, scene):
    """evaluate_run's depth figures alone ({"mae" in the depth files' units, "relative", "frames",
    "pixels"}, None without depth maps) over the test frames, without the rest of an evaluation."""
    rows = []
    for k in scene.test_indices:
        f = scene.frames[k]
        h = render(rt, params, f.camera, f.time).host()
        rows.append({"depth": _depth_row(h["depth"], h["alpha"], f)})
    return _depth_summary(rows, scene.world_scale)

# ------------------------------------------------------------------------------ flow vs gt_flow
def flow_references(scene) -> dict:
    """{k: (gt flow, valid, dis epe)} for each test frame k that has scene/gt_flow/<name>.npy (the
    forward flow from frame k to k + 1 written by ``endowave-cl synth``); {} for scenes without it.

    gt flow is resized to the scene size (vectors scaled) for downscaled scenes.  valid: the pixels
    both errors are averaged over: the target p + flow inside the image and, with masks, tissue at p
    in frame k and tissue at p and at the target in frame k + 1 (``data.flow.valid_mask``, tool
    grown by a pixel): the model is scored on tissue only, like its images.  dis epe: the mean
    end-point error there of OpenCV DIS run on frames k and k + 1 themselves (the estimator and
    preset of the pseudo ground truth), a reference of what a flow estimator that sees both frames
    gets.  Cached in memory per scene path, size and split."""
    gt_dir = Path(scene.path) / "gt_flow"
    if not gt_dir.is_dir():
        return {}
    key = (str(Path(scene.path).resolve()), scene.width, scene.height, tuple(scene.test_indices))
    if key in _FLOW_CACHE:
        return _FLOW_CACHE[key]
    refs = {}
    for k in scene.test_indices:
        if k + 1 >= len(scene.frames):
            continue
        path = gt_dir / f"{scene.frames[k].name}.npy"
        if not path.is_file():
            continue
        try:
            gt = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise DataError(f"{path}: unreadable ground-truth flow ({e})") from None
        if gt.ndim != 3 or gt.shape[2] != 2:
            raise DataError(f"{path}: ground-truth flow must be [H, W, 2], got {list(gt.shape)}")
        gt = _fit_to_scene(gt.astype(np.float32), path, scene)
        f0, f1 = scene.frames[k], scene.frames[k + 1]
        valid = valid_mask(gt, None, f0.mask, f1.mask) > 0.5
        if not valid.any():
            continue
        dis = estimate_flow(f0.image, f1.image)
        refs[k] = (gt, valid, _epe(dis, gt, valid))
    _FLOW_CACHE[key] = refs
    return refs


def _epe(flow, gt, valid) -> float:
    return float(np.linalg.norm(flow - gt, axis=-1)[valid].mean())


def _flow_row(rendered, ref) -> dict:
    gt, valid, dis_epe = ref
    return {"model_epe": _epe(rendered, gt, valid), "dis_epe": dis_epe,
            "model_magnitude": float(np.linalg.norm(rendered, axis=-1)[valid].mean()),
            "gt_magnitude": float(np.linalg.norm(gt, axis=-1)[valid].mean()),
            "pixels": int(valid.sum())}


def _flow_summary(rows) -> dict:
    """Means over the test frames with ground truth; gt_magnitude is also the error of zero flow."""
    fl = [r["flow"] for r in rows if "flow" in r]
    out = {key: float(np.mean([f[key] for f in fl])) for key in
           ("model_epe", "dis_epe", "model_magnitude", "gt_magnitude")}
    out.update({"frames": len(fl), "pixels": int(sum(f["pixels"] for f in fl))})
    return out


# ------------------------------------------------------------------------------ figures
def per_frame_plot_png(m: dict, title: str = "") -> bytes:
    """PNG bytes: whole-image PSNR of each test frame over time, the model and (when evaluated)
    the baselines, with each curve's mean in the legend."""
    import matplotlib      # on first use: about 1 s to import, for the figures alone
    matplotlib.use("Agg")
    from matplotlib.figure import Figure
    rows = m["per_frame"]
    idx = [r["index"] for r in rows]
    fig = Figure(figsize=(7.0, 4.4), dpi=110)
    ax = fig.add_subplot(1, 1, 1)
    curves = [("model", "model", "o-")] + [(name, LABELS[name], s) for name, s in
                                           (("mean", "s--"), ("dis", "^--"), ("dis_cubic", "v--"), ("teacher", "d--"))
                                           if name in rows[0]]
    for key, label, style in curves:
        vals = [r[key]["psnr"] for r in rows]
        ax.plot(idx, vals, style, label=f"{label} (mean {np.mean(vals):.2f} dB)", markersize=4)
    ax.set_xlabel(f"{m.get('split', 'test')} frame index (time order)")
    ax.set_ylabel("PSNR, whole image of masked images (dB)")
    if title:
        ax.set_title(title, fontsize=9)
    ax.grid(True, alpha=0.3)
    # below the axes, so that no curve's points are hidden behind it
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=2, frameon=False)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def worst_frame(m: dict) -> int:
    """Index of the test frame where the model's whole-image PSNR is lowest."""
    return min(m["per_frame"], key=lambda r: r["model"]["psnr"])["index"]


def error_panel_image(pred: np.ndarray, frame) -> np.ndarray:
    """[LABEL_HEIGHT + H, 3W + 2 gaps, 3] float RGB: a strip naming the panels above ground truth |
    render | error, full resolution.  The error is
    mean |render - gt| over RGB (tool pixels of a masked scene set to 0, as scored), through the
    inferno colour map, saturating at ERROR_FULL_SCALE."""
    pred = np.clip(np.asarray(pred, np.float32), 0, 1)
    gt = frame.image
    err = np.abs(pred - gt).mean(-1)
    if frame.mask is not None:
        err = err * frame.mask
    e8 = np.clip(err / ERROR_FULL_SCALE * 255 + 0.5, 0, 255).astype(np.uint8)
    heat = cv2.applyColorMap(e8, cv2.COLORMAP_INFERNO)[..., ::-1].astype(np.float32) / 255.0   # BGR -> RGB
    gap = np.ones((gt.shape[0], 4, 3), np.float32)
    panels = np.concatenate([gt, gap, pred, gap, heat], 1)
    return np.concatenate([_label_strip(panels.shape[1], gt.shape[1], 4,
                                        ("ground truth", "model", f"|error|, full scale {ERROR_FULL_SCALE:g}")),
                           panels], 0)


LABEL_HEIGHT = 16   # px: the strip above the worst-frame panels that names them


def _label_strip(width: int, panel: int, gap: int, labels) -> np.ndarray:
    """[LABEL_HEIGHT, width, 3] float RGB, white, each label in black at the left of its panel
    (shrunk to fit a narrow panel)."""
    strip = np.full((LABEL_HEIGHT, width, 3), 255, np.uint8)
    for i, text in enumerate(labels):
        scale = 0.4
        while scale > 0.2 and cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] > panel - 4:
            scale -= 0.05
        cv2.putText(strip, text, (i * (panel + gap) + 2, LABEL_HEIGHT - 4), cv2.FONT_HERSHEY_SIMPLEX, scale,
                    (0, 0, 0), 1, cv2.LINE_AA)
    return strip.astype(np.float32) / 255.0


def write_figures(run_dir, rt, params, scene, m: dict, title: str = "") -> Dict[str, str]:
    """Write RUN/eval_per_frame.png and RUN/eval_worst.png (both atomically); return their paths."""
    run_dir = Path(run_dir)
    plot = run_dir / "eval_per_frame.png"
    write_bytes_atomic(plot, per_frame_plot_png(m, title))
    k = worst_frame(m)
    f = scene.frames[k]
    pred = render(rt, params, f.camera, f.time, select=True).host()["image"]
    worst = run_dir / "eval_worst.png"
    write_png_atomic(worst, error_panel_image(pred, f))
    return {"per_frame_plot": str(plot), "worst_frame_image": str(worst), "worst_frame": k}


def _render_fps(rt, params, f, runs: int) -> float:
    for _ in range(3):
        render(rt, params, f.camera, f.time, select=True)
    rt.queue.finish()
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        render(rt, params, f.camera, f.time, select=True)
        rt.queue.finish()
        ts.append(time.perf_counter() - t0)
    return 1.0 / statistics.median(ts)
