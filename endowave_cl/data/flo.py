"""Optical flow files: Middlebury ``.flo`` and numpy ``.npy``, both [H, W, 2] float32 (x, y) in pixels.

.flo layout (little-endian): float32 magic 202021.25, int32 width, int32 height, then
height * width * 2 float32 values, row-major, (u, v) interleaved.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DataError
from ..atomic import write_bytes_atomic

FLO_MAGIC = 202021.25


def read_flo(path) -> np.ndarray:
    """[H, W, 2] float32 from a Middlebury .flo file."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise DataError(f"{path}: cannot read ({e.strerror})") from None
    if len(data) < 12:
        raise DataError(f"{path}: too short for a .flo header")
    magic = np.frombuffer(data, "<f4", 1)[0]
    if magic != np.float32(FLO_MAGIC):
        raise DataError(f"{path}: not a .flo file (magic {magic!r}, expected {FLO_MAGIC})")
    w, h = (int(v) for v in np.frombuffer(data, "<i4", 2, offset=4))
    if w <= 0 or h <= 0:
        raise DataError(f"{path}: bad size {w}x{h} in the .flo header")
    need = 12 + 8 * w * h
    if len(data) != need:
        raise DataError(f"{path}: {len(data)} bytes, a {w}x{h} .flo file has {need} (truncated?)")
    return np.frombuffer(data, "<f4", 2 * w * h, offset=12).reshape(h, w, 2).astype(np.float32)


def write_flo(path, flow: np.ndarray) -> None:
    """Write [H, W, 2] flow as a Middlebury .flo file (atomically)."""
    flow = np.asarray(flow, np.float32)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"flow must be [H, W, 2], got {flow.shape}")
    h, w = flow.shape[:2]
    header = np.array([FLO_MAGIC], "<f4").tobytes() + np.array([w, h], "<i4").tobytes()
    write_bytes_atomic(path, header + flow.astype("<f4").tobytes())


def read_flow_file(path) -> np.ndarray:
    """[H, W, 2] float32 from a .flo or .npy file; errors name the file."""
    path = Path(path)
    if path.suffix.lower() == ".flo":
        flow = read_flo(path)
    elif path.suffix.lower() == ".npy":
        try:
            flow = np.load(path, allow_pickle=False)
        except Exception as e:
            raise DataError(f"{path}: not a readable .npy file ({e})") from None
        if flow.dtype.kind not in "fiu":
            raise DataError(f"{path}: flow must hold numbers, got dtype {flow.dtype}")
        if flow.ndim != 3 or flow.shape[2] != 2:
            raise DataError(f"{path}: expected flow of shape (H, W, 2), got {flow.shape}")
        flow = flow.astype(np.float32)
    else:
        raise DataError(f"{path}: unknown flow file type (use .flo or .npy)")
    if not np.all(np.isfinite(flow)):
        raise DataError(f"{path}: flow contains NaN or infinite values")
    return flow
