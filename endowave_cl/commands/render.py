"""Render a trained run: the test frames (PNG), depth images (16-bit PNG, depth x 1000, and a
colour-mapped PNG beside each: turbo, red = near, one range for all frames) and a video of every
frame in time order (H.264 in MP4, which browsers play), written under RUN/render/ (each file
written to a temporary name and renamed)."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from ..atomic import stale_temporaries, write_png_atomic
from ..errors import EndowaveError
from ..gaussians import upload
from ..progress import progress as progress_bar
from ..render import render
from ..run_io import load_run
from ..runtime import get_runtime
from ..video import depth_colour, depth_range, write_video

DEPTH_PNG_SCALE = 1000.0   # 16-bit depth PNGs store depth x 1000 in the units of the scene's files
                           # (millimetres when they are in metres)


FPS_RANGE = (0.1, 1000.0)  # video frame rates both encoders (H.264, mp4v) write


def add_arguments(p) -> None:
    p.add_argument("run", help="run folder written by endowave-cl train")
    p.add_argument("--scene", help="scene folder (default: the one the run was trained on)")
    p.add_argument("--all", action="store_true", help="render every frame, not only the test frames")
    p.add_argument("--no-video", action="store_true", help="skip the video")
    p.add_argument("--fps", type=float, default=15.0, help="video frame rate")


def run(args) -> int:
    if not (math.isfinite(args.fps) and args.fps > 0):
        raise EndowaveError(f"--fps must be a positive number, got {args.fps}")
    if not (args.no_video or FPS_RANGE[0] <= args.fps <= FPS_RANGE[1]):   # the encoders fail outside it (issue 57)
        raise EndowaveError(f"--fps must be from {FPS_RANGE[0]:g} to {FPS_RANGE[1]:g} frames per second, got {args.fps:g}")
    r = load_run(args.run, args.scene)
    rt = get_runtime(getattr(args, "device", None))
    params = upload(rt, r.gaussians)
    out = Path(args.run) / "render"
    for folder in (out, out / "frames", out / "depth", out / "depth_colour"):   # left by a killed render
        for p in stale_temporaries(folder):
            p.unlink()
    frames = r.scene.frames
    idx = range(len(frames)) if args.all else r.scene.test_indices
    video_frames = []
    depths = []          # (name, depth in file units, valid) of the written frames, coloured at the end
    for k in progress_bar(range(len(frames)), desc="render", unit="frame"):
        f = frames[k]
        if k not in idx and args.no_video:
            continue
        h = render(rt, params, f.camera, f.time, select=True).host()
        img = np.clip(h["image"], 0, 1)
        if k in idx:
            write_png_atomic(out / "frames" / f"{f.name or k:0>6}.png", img)
            d = h["depth"] / np.maximum(h["alpha"], 1e-6) / r.scene.world_scale   # [H, W] file units
            depths.append((f"{f.name or k:0>6}.png", d, h["alpha"] > 0.5))
            d = np.clip(d * DEPTH_PNG_SCALE, 0, 65535).astype(np.uint16)
            write_png_atomic(out / "depth" / f"{f.name or k:0>6}.png", d)
        if not args.no_video:
            video_frames.append((img * 255 + 0.5).astype(np.uint8))
    colour_note = ""
    if depths:
        lo, hi = depth_range([d for _, d, _ in depths], [v for _, _, v in depths])
        for name, d, valid in depths:
            write_png_atomic(out / "depth_colour" / name, depth_colour(d, valid, lo, hi))
        colour_note = f"; depth_colour/ = turbo, red = near {lo:.4g}, blue = far {hi:.4g} (file units)"
    if video_frames:
        path = out / "video.mp4"
        try:
            codec = write_video(path, video_frames, args.fps)
        except (OSError, ValueError, RuntimeError) as e:
            why = next((ln.strip() for ln in str(e).splitlines() if ln.strip() and "STDERR" not in ln), type(e).__name__)
            print(f"warning: video not written ({why}); the frames are written as PNG", file=sys.stderr)
        else:
            what = "H.264" if codec == "h264" else ("MPEG-4 Part 2: imageio-ffmpeg is missing, so browsers "
                                                    "will not play it; pip install imageio-ffmpeg")
            print(f"video: {path} ({what})")
    print(f"wrote {len(list(idx))} frames and depth images under {out} (depth PNG = depth x {DEPTH_PNG_SCALE:g}"
          f"{colour_note})")
    return 0
