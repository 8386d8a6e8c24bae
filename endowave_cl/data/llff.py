"""poses_bounds.npy (LLFF / EndoNeRF): poses, intrinsics and bounds, converted to the OpenCV convention.

Each row of ``poses_bounds.npy`` [N, 17] is a 3x5 matrix flattened row-major, then (near, far).
The 3x5 matrix is [R | t | hwf]: R, t camera-to-world with LLFF's camera axes, i.e. the columns
of R are the camera's (down, right, backwards) directions in world coordinates; the last column is
(H, W, focal) for EndoNeRF, or (cy, cx, focal) for StereoMIS scenes converted to this layout.

Conversion.  OpenCV camera axes are (right, down, forward) = (LLFF col 1, LLFF col 0, -LLFF col 2),
so ``R_cv = R Q`` with Q below.  We also re-express the *world* in the same relabelled axes
(``x_new = Q^T x_old``, a proper rotation, det Q = +1): the camera-to-world becomes
``[Q^T R Q | Q^T t]``.  Hence the identity pose that EndoNeRF stores for its static endoscope gives
the identity world->camera matrix: the camera sits at the origin looking down +z and the tissue has
z in [near, far] in front of it.  (EndoNeRF-style loaders such as Deform3DGS instead flip the y and z
columns, which leaves an identity pose looking down -z; we choose +z so the world frame of a static
scene is simply the camera frame.)
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DataError

# cv camera axes expressed in LLFF camera axes: x_llff = Q @ x_cv
Q_LLFF_FROM_CV = np.array([[0.0, 1.0, 0.0],
                           [1.0, 0.0, 0.0],
                           [0.0, 0.0, -1.0]])

HWF_LAYOUTS = ("auto", "hwf", "cy_cx_f")


def read_poses_bounds(path) -> np.ndarray:
    """Read and validate ``poses_bounds.npy``; returns [N, 17] float64."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: missing (every EndoNeRF-layout scene needs poses_bounds.npy)")
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception as e:  # numpy raises ValueError / OSError / EOFError for bad files
        raise DataError(f"{path}: not a readable .npy file ({e})") from None
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] == 0:
        raise DataError(f"{path}: expected an array of shape (N, 17), got {arr.shape}")
    arr = _as_float(arr, path)
    bad = ~np.all(np.isfinite(arr), axis=1)
    if bad.any():
        raise DataError(f"{path}: row {int(np.argmax(bad))} contains NaN or infinite values")
    for i in range(arr.shape[0]):
        check_rotation(arr[i, :15].reshape(3, 5)[:, :3], f"{path} (row {i})")
    return arr


# How far R^T R may be from the identity (max abs entry) and det R from +1.  Poses stored as float32
# (COLMAP / LLFF) are orthonormal to ~1e-7; a pose matrix scaled or sheared by more than this is a
# broken file, not rounding, and would silently scale or mirror the scene.
ROTATION_TOL = 1e-3


def check_rotation(R: np.ndarray, source) -> None:
    """DataError naming ``source`` unless R (3x3) is a proper rotation within ROTATION_TOL."""
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if not err <= ROTATION_TOL:
        raise DataError(f"{source}: the pose rotation is not orthonormal (|R^T R - I| = {err:.3g}, "
                        f"det {det:.3g}; tolerance {ROTATION_TOL:g})")
    if not abs(det - 1.0) <= ROTATION_TOL:
        raise DataError(f"{source}: the pose rotation has determinant {det:.3g}, not +1 (a reflection)")


def _as_float(arr: np.ndarray, path: Path) -> np.ndarray:
    """float64 copy of a numeric array, or of one stored as text holding numbers; else DataError
    naming the first row that is not numbers."""
    kind = arr.dtype.kind
    if kind in "iuf":
        return arr.astype(np.float64)
    if kind in "US":
        for i, row in enumerate(arr):
            try:
                row.astype(np.float64)
            except ValueError:
                bad = next(v.item() for v in row if not _is_number(v))
                raise DataError(f"{path}: row {i} holds {bad!r}, not a number "
                                f"(poses are stored as text, dtype {arr.dtype})") from None
        return arr.astype(np.float64)
    raise DataError(f"{path}: row 0 is not numbers (dtype {arr.dtype}; poses must be stored as floats)")


def _is_number(v) -> bool:
    try:
        float(v)
        return True
    except ValueError:
        return False


def llff_to_viewmat(pose34: np.ndarray) -> np.ndarray:
    """LLFF camera-to-world [3, 4] -> OpenCV world-to-camera [4, 4] (see the module docstring)."""
    Q = Q_LLFF_FROM_CV
    R = pose34[:, :3]
    t = pose34[:, 3]
    c2w = np.eye(4)
    c2w[:3, :3] = Q.T @ R @ Q
    c2w[:3, 3] = Q.T @ t
    return np.linalg.inv(c2w).astype(np.float32)


def intrinsics_from_hwf(hwf: np.ndarray, width: int, height: int, layout: str, source) -> tuple:
    """(fx, fy, cx, cy) in pixels of the full-size image from one hwf column.

    ``layout``: "hwf" (EndoNeRF: H, W, f; principal point at the image centre), "cy_cx_f"
    (StereoMIS conversions: cy, cx, f), or "auto": "hwf" when (H, W) equal the image size, else
    "cy_cx_f" when (cy, cx) lie inside the image, else an error.
    """
    a, b, f = (float(v) for v in hwf)
    if layout not in HWF_LAYOUTS:
        raise DataError(f"{source}: unknown hwf layout {layout!r} (choose from {', '.join(HWF_LAYOUTS)})")
    if not f > 0:
        raise DataError(f"{source}: focal length {f} is not positive")
    if layout == "auto":
        if round(a) == height and round(b) == width:
            layout = "hwf"
        elif 0 < a < height and 0 < b < width:
            layout = "cy_cx_f"
        else:
            raise DataError(f"{source}: hwf column ({a:g}, {b:g}, {f:g}) matches neither the image size "
                            f"{width}x{height} (H, W, f) nor a principal point inside it (cy, cx, f)")
    if layout == "hwf":
        if round(a) != height or round(b) != width:
            raise DataError(f"{source}: hwf says {round(b)}x{round(a)} but the images are {width}x{height}")
        return f, f, width / 2.0, height / 2.0
    if not (0 < a < height and 0 < b < width):
        raise DataError(f"{source}: principal point (cx={b:g}, cy={a:g}) lies outside the "
                        f"{width}x{height} image")
    return f, f, b, a
