"""Videos that play everywhere (H.264 in MP4) and colour-mapped depth images.

OpenCV's own writer only has MPEG-4 Part 2 (``mp4v``), which browsers do not play.  H.264 comes
from the FFmpeg binary that the ``imageio-ffmpeg`` wheel ships (libx264, yuv420p, ``+faststart``
so a browser can start before the whole file is read); nothing is downloaded at run time.  Without
it (a platform with no wheel) the OpenCV writer is used and the caller is told the codec.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Optional, Tuple

import cv2
import numpy as np

from .atomic import default_file_mode, temp_prefix

H264_CRF = 18          # visually lossless for renders; libx264's default is 23


def _even(frame: np.ndarray) -> np.ndarray:
    """Pad [H, W, 3] to even sides by repeating the last row / column (yuv420p needs even sizes)."""
    h, w = frame.shape[:2]
    ph, pw = h % 2, w % 2
    if ph or pw:
        frame = np.pad(frame, ((0, ph), (0, pw), (0, 0)), mode="edge")
    return np.ascontiguousarray(frame)


def h264_available() -> bool:
    try:
        import imageio_ffmpeg     # where it is used: without it render writes mp4v (write_video)
        imageio_ffmpeg.get_ffmpeg_exe()
        return True
    except Exception:  # noqa: BLE001  not installed, or no binary for this platform
        return False


def _write_h264(tmp: Path, frames, fps: float, size: Tuple[int, int]) -> None:
    import imageio_ffmpeg
    w, h = size
    writer = imageio_ffmpeg.write_frames(str(tmp), (w + w % 2, h + h % 2), fps=fps, codec="libx264",
                                         pix_fmt_in="rgb24", pix_fmt_out="yuv420p", quality=None,
                                         macro_block_size=1, ffmpeg_log_level="error",
                                         output_params=["-crf", str(H264_CRF), "-movflags", "+faststart"])
    writer.send(None)
    try:
        for fr in frames:
            writer.send(_even(fr).tobytes())
    finally:
        writer.close()


def _write_mp4v(tmp: Path, frames, fps: float, size: Tuple[int, int]) -> None:
    vw = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
    try:
        for fr in frames:
            vw.write(np.ascontiguousarray(fr[..., ::-1]))
    finally:
        vw.release()


def write_video(path, frames: Iterable[np.ndarray], fps: float, codec: Optional[str] = None) -> str:
    """Write RGB uint8 frames [H, W, 3] (all one size) to ``path`` (.mp4) atomically; returns the
    codec used: "h264", or "mp4v" (OpenCV's MPEG-4 Part 2) when imageio-ffmpeg is missing or
    ``codec="mp4v"``.  Raises OSError when nothing could be written."""
    frames = list(frames)
    if not frames:
        raise ValueError("no frames")
    path = Path(path)
    h, w = frames[0].shape[:2]
    use = codec or ("h264" if h264_available() else "mp4v")
    tmp = path.parent / f"{temp_prefix(path.name)}w.tmp.mp4"   # pid in the name: stale ones are removed
    try:
        (_write_h264 if use == "h264" else _write_mp4v)(tmp, frames, fps, (w, h))
        if not (tmp.is_file() and tmp.stat().st_size > 0):
            raise OSError(f"{path}: the {use} encoder wrote nothing")
        os.chmod(tmp, default_file_mode())
        os.replace(tmp, path)
    except BaseException:
        if tmp.exists():
            tmp.unlink()
        raise
    return use


def video_codec(path) -> str:
    """The codec name of a video's first stream as OpenCV reports it (e.g. "h264"), "" if unreadable."""
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            return ""
        fourcc = int(cap.get(cv2.CAP_PROP_FOURCC))
        return fourcc.to_bytes(4, "little").decode("ascii", "replace").strip("\x00 ").lower()
    finally:
        cap.release()


def depth_colour(depth: np.ndarray, valid: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """[H, W, 3] uint8 RGB: the turbo colour map, red = near (lo), blue = far (hi), black = no depth."""
    span = max(hi - lo, 1e-12)
    u = np.clip((hi - depth) / span, 0.0, 1.0)
    bgr = cv2.applyColorMap((u * 255 + 0.5).astype(np.uint8), cv2.COLORMAP_TURBO)
    bgr[~valid] = 0
    return bgr[..., ::-1]


def depth_range(depths, valids, percentiles=(1.0, 99.0)) -> Tuple[float, float]:
    """(near, far) for colouring: the percentiles of every map's valid depths (one range for all)."""
    vals = [d[v] for d, v in zip(depths, valids) if v.any()]
    if not vals:
        return 0.0, 1.0
    lo, hi = np.percentile(np.concatenate(vals), percentiles)
    return float(lo), float(max(hi, lo + 1e-6))
