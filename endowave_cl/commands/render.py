"""Render a trained run: the test frames (PNG), depth images (16-bit PNG) and a video of every
frame in time order, written under RUN/render/ (each file written to a temporary name and renamed)."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

DEPTH_PNG_SCALE = 1000.0   # 16-bit depth PNGs store depth x 1000 in the units of the scene's files
                           # (millimetres when they are in metres)


def add_arguments(p) -> None:
    p.add_argument("run", help="run folder written by endowave-cl train")
    p.add_argument("--scene", help="scene folder (default: the one the run was trained on)")
    p.add_argument("--all", action="store_true", help="render every frame, not only the test frames")
    p.add_argument("--no-video", action="store_true", help="skip the video")
    p.add_argument("--fps", type=float, default=15.0, help="video frame rate")


def run(args) -> int:
    import cv2

    from ..gaussians import upload
    from ..progress import progress as progress_bar
    from ..render import render
    from ..atomic import write_png_atomic
    from ..run_io import load_run
    from ..runtime import get_runtime

    import math
    from ..errors import EndowaveError
    if not (math.isfinite(args.fps) and args.fps > 0):
        raise EndowaveError(f"--fps must be a positive number, got {args.fps}")
    r = load_run(args.run, args.scene)
    rt = get_runtime(getattr(args, "device", None))
    params = upload(rt, r.gaussians)
    out = Path(args.run) / "render"
    from ..atomic import stale_temporaries
    for folder in (out, out / "frames", out / "depth"):   # left by a killed render
        for p in stale_temporaries(folder):
            p.unlink()
    frames = r.scene.frames
    idx = range(len(frames)) if args.all else r.scene.test_indices
    video_frames = []
    for k in progress_bar(range(len(frames)), desc="render", unit="frame"):
        f = frames[k]
        if k not in idx and args.no_video:
            continue
        h = render(rt, params, f.camera, f.time, select=True).host()
        img = np.clip(h["image"], 0, 1)
        if k in idx:
            write_png_atomic(out / "frames" / f"{f.name or k:0>6}.png", img)
            d = h["depth"] / np.maximum(h["alpha"], 1e-6) / r.scene.world_scale   # [H, W] file units
            d = np.clip(d * DEPTH_PNG_SCALE, 0, 65535).astype(np.uint16)
            write_png_atomic(out / "depth" / f"{f.name or k:0>6}.png", d)
        if not args.no_video:
            video_frames.append((img * 255 + 0.5).astype(np.uint8)[..., ::-1])
    if video_frames:
        path = out / "video.mp4"
        from ..atomic import default_file_mode, temp_prefix
        tmp = out / f"{temp_prefix('video.mp4')}w.tmp.mp4"   # pid in the name: stale ones are removed
        hgt, wid = video_frames[0].shape[:2]
        vw = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), args.fps, (wid, hgt))
        for fr in video_frames:
            vw.write(fr)
        vw.release()
        if tmp.is_file() and tmp.stat().st_size > 0:
            os.chmod(tmp, default_file_mode())
            os.replace(tmp, path)
            print(f"video: {path}")
        else:
            if tmp.exists():
                tmp.unlink()
            print("video: OpenCV could not write mp4 here; frames are written as PNG")
    print(f"wrote {len(list(idx))} frames and depth images under {out} (depth PNG = depth x {DEPTH_PNG_SCALE:g})")
    return 0
