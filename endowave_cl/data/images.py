"""Reading PNG frames, depth maps and tool masks with errors that name the file."""
from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from ..errors import DataError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def natural_key(name: str):
    """Sort key that orders the numbers in a name by value: 0, 1, 2, ..., 10, 11 (not 0, 1, 10, 11,
    2); zero-padded names sort as before.  The name itself breaks ties (01 / 1)."""
    parts = re.split(r"(\d+)", name)
    return tuple(int(p) if i % 2 else p for i, p in enumerate(parts)), name


def list_images(folder: Path) -> list:
    """Image files of ``folder`` in frame order: by name, numbers by value (natural_key); frames are
    paired across folders by this order."""
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                  key=lambda p: natural_key(p.name))


def _decode(path: Path, flags: int) -> np.ndarray:
    try:
        data = path.read_bytes()
    except OSError as e:
        raise DataError(f"{path}: cannot read ({e.strerror})") from None
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)  # we report the failure ourselves
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), flags) if data else None
    finally:
        cv2.utils.logging.setLogLevel(level)
    if img is None:
        raise DataError(f"{path}: unreadable or truncated image")
    return img


def read_rgb(path: Path) -> np.ndarray:
    """[H, W, 3] float32 RGB in [0, 1] (8- or 16-bit files; grey is replicated, alpha dropped)."""
    img = _decode(path, cv2.IMREAD_UNCHANGED)
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    if img.dtype not in (np.uint8, np.uint16):
        raise DataError(f"{path}: unsupported pixel type {img.dtype}")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 4:
        img = img[:, :, :3]
    elif img.shape[2] != 3:
        raise DataError(f"{path}: {img.shape[2]} channels, expected 1, 3 or 4")
    return (img[:, :, ::-1].astype(np.float32) / scale)  # BGR -> RGB


def read_depth_raw(path: Path) -> np.ndarray:
    """[H, W] float32 raw values of an 8- or 16-bit depth PNG (first channel if several)."""
    img = _decode(path, cv2.IMREAD_UNCHANGED)
    if img.dtype not in (np.uint8, np.uint16):
        raise DataError(f"{path}: depth must be 8- or 16-bit, got {img.dtype}")
    if img.ndim == 3:
        img = img[:, :, 0]
    return img.astype(np.float32)


def read_tissue_mask(path: Path) -> np.ndarray:
    """[H, W] float32, 1 = tissue (supervise), 0 = tool.  Files store 255 (or 65535) on tool pixels."""
    img = _decode(path, cv2.IMREAD_UNCHANGED)
    if img.dtype not in (np.uint8, np.uint16):
        raise DataError(f"{path}: mask must be 8- or 16-bit, got {img.dtype}")
    if img.ndim == 3:
        img = img[:, :, :3].max(axis=2)
    half = (np.iinfo(img.dtype).max + 1) // 2
    return (img < half).astype(np.float32)
