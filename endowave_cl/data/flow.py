"""Pseudo ground-truth optical flow between consecutive training frames (the paper uses GMFlow,
whose weights cannot be downloaded here; we use OpenCV's classical estimators).

For each training frame k and the next training frame k' (consecutive in ``scene.train_indices``):
forward flow k -> k', backward flow k' -> k, and a valid mask per direction:

    valid(p) = forward-backward consistent (Sundaram et al. 2010):
                 |f_fw(p) + f_bw(p + f_fw(p))|^2 < 0.01 (|f_fw(p)|^2 + |f_bw(p + f_fw(p))|^2) + 0.5
               AND p + f_fw(p) inside the image
               AND (scenes with masks) tissue at p in frame k, and at p and at p + f_fw(p) in
                   frame k', with the tool masks grown by TOOL_MARGIN pixels

Why also "tissue at p in frame k'": a tissue pixel about to be covered by the tool has no true
match, and the estimators then give it a smoothed flow that often points off the tool onto tissue
that is consistent backwards (measured on the synthetic scene: the forward-backward test alone
rejects only 35-55 % of such pixels); the tool moves much faster than the tissue, so excluding
pixels the tool covers in either frame removes them (100 % there) at the cost of a thin band of
tissue around the tool (about 1-2 % of the tissue pixels).

Cache: results are stored under ``<cache root>/<key>/`` where the cache root is ``cache_dir``,
else ``$ENDOWAVE_CL_CACHE/flow``, else ``$XDG_CACHE_HOME/endowave-cl/flow`` (default
``~/.cache/endowave-cl/flow``); never inside the scene (the shared data is read-only).  The key is
a SHA-256 of the method, its settings, the image size, the frame pairs and the exact 8-bit grey
frames and masks the estimator sees, so any change to the frames, the downscale or the method gives
a new key (stale entries are simply not used).

User flow: if ``<scene>/flow/`` holds files, they are used instead of computing any: for each pair,
``flow/<src>_<dst>.npy`` or ``.flo`` with ``<src>``, ``<dst>`` the image file stems (for example
``flow/000000_000002.flo`` is the flow from images/000000.png to images/000002.png), [H, W, 2] in
pixels at the full image size (resized and rescaled for a downscaled scene).  The backward file
``<dst>_<src>`` is optional: without it the consistency check is skipped for that pair.
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from .. import env     # every ENDOWAVE_* variable is parsed there, with a named error
from ..errors import DataError
from ..atomic import atomic_directory
from ..progress import progress as progress_bar
from .flo import read_flow_file

METHODS = ("dis", "dis_fine", "farneback", "deepflow", "tvl1")
CACHE_VERSION = 1                     # bump when the computation or the stored format changes
# Sundaram et al. 2010 forward-backward thresholds (DESIGN.md)
FB_REL, FB_ABS = 0.01, 0.5
# a bilinearly sampled mask value counts as tissue only if every neighbour involved is tissue
TISSUE_KEEP = 0.999
# tool masks are grown by this many pixels before use: estimators blur motion boundaries and the
# mask edge is only known to the nearest pixel
TOOL_MARGIN = 1
# the estimators need frames of some size: DIS fails below its 8-pixel patches plus a margin; a
# flow_max_pixels under this many is refused (train/config.py, the flow command) and no side of
# the estimation size goes under MIN_ESTIMATION_SIDE
MIN_ESTIMATION_PIXELS = 256
MIN_ESTIMATION_SIDE = 16
# user and ground-truth flow vectors longer than this many frame sizes are refused (a flow that
# carries every pixel far out of the frame is a unit or format mistake, not motion)
MAX_FLOW_FRAMES = 2.0


@dataclass
class FlowPair:
    src: int                 # frame index k
    dst: int                 # next training frame index k'
    flow: np.ndarray         # [H, W, 2] float32, pixels (x, y), from k to k'
    valid: np.ndarray        # [H, W] float32, 1 = supervise (consistent, inside, tissue in both)
    flow_bw: np.ndarray      # [H, W, 2] float32, from k' to k
    valid_bw: np.ndarray     # [H, W] float32, the same test in the other direction


class SceneFlow(dict):
    """``{k: FlowPair}`` keyed by the source training frame, plus where it came from."""
    method: str = ""
    cache_path: Optional[Path] = None     # the cache entry used or written (None: not cached)
    computed: bool = False                # True if the estimator ran in this call


# ---------------------------------------------------------------------------------------------
def to_grey8(image: np.ndarray) -> np.ndarray:
    """[H, W, 3] float RGB in [0, 1] -> [H, W] uint8 grey, what the estimators see."""
    rgb8 = np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return cv2.cvtColor(rgb8, cv2.COLOR_RGB2GRAY)


class _Farneback:
    """OpenCV's Farneback estimator behind the ``calc(grey0, grey1, None)`` call of the others:
    5 pyramid levels at scale 0.5, 15 px window, 5 iterations, 7 px polynomial neighbourhood."""

    def calc(self, grey0, grey1, _flow):
        return cv2.calcOpticalFlowFarneback(grey0, grey1, None, 0.5, 5, 15, 5, 7, 1.5, 0)


def _make_estimator(method: str):
    if method == "dis":
        return cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    if method == "dis_fine":
        # DIS down to the full-resolution level, with smaller, denser patches and more descent
        # iterations than the preset: slower (about 4x), and sharper at motion boundaries
        e = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        e.setFinestScale(0)
        e.setGradientDescentIterations(50)
        e.setPatchSize(8)
        e.setPatchStride(3)
        return e
    if method == "farneback":
        return _Farneback()
    if method == "deepflow":
        return cv2.optflow.createOptFlow_DeepFlow()
    if method == "tvl1":
        return cv2.optflow.DualTVL1OpticalFlow_create()
    raise DataError(f"unknown flow method {method!r} (choose from {', '.join(METHODS)})")


def _estimate(estimator, grey0: np.ndarray, grey1: np.ndarray) -> np.ndarray:
    """The OpenCV call: [H, W] uint8 x 2 -> [H, W, 2] float32 flow from grey0 to grey1."""
    return estimator.calc(grey0, grey1, None)


def estimate_flow(image0: np.ndarray, image1: np.ndarray, method: str = "dis") -> np.ndarray:
    """[H, W, 2] float32 flow from image0 to image1 ([H, W, 3] float RGB in [0, 1])."""
    return np.asarray(_estimate(_make_estimator(method), to_grey8(image0), to_grey8(image1)), np.float32)


# ---------------------------------------------------------------------------------------------
def _targets(flow):
    h, w = flow.shape[:2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return u + flow[..., 0], v + flow[..., 1]


def _inside(x, y, w, h):
    return (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)


def fb_consistent(fw: np.ndarray, bw: np.ndarray) -> np.ndarray:
    """[H, W] bool: the Sundaram forward-backward test for the forward flow ``fw`` [H, W, 2]
    given the backward flow ``bw`` [H, W, 2]; targets outside the image fail."""
    h, w = fw.shape[:2]
    x, y = _targets(fw)
    bw_at = cv2.remap(bw.astype(np.float32), x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    diff = fw + bw_at
    lhs = (diff ** 2).sum(-1)
    rhs = FB_REL * ((fw ** 2).sum(-1) + (bw_at ** 2).sum(-1)) + FB_ABS
    return (lhs < rhs) & _inside(x, y, w, h)


def valid_mask(fw, bw=None, mask0=None, mask1=None) -> np.ndarray:
    """[H, W] float32 valid mask of the forward flow ``fw`` (see the module docstring).

    bw: backward flow or None (no consistency test); mask0/mask1: [H, W] tissue masks (1 = tissue)
    of the source and target frames, or None."""
    h, w = fw.shape[:2]
    x, y = _targets(fw)
    ok = fb_consistent(fw, bw) if bw is not None else _inside(x, y, w, h)
    if mask0 is not None:
        ok &= shrink_tissue(mask0) > 0.5
    if mask1 is not None:
        t1 = shrink_tissue(mask1)
        ok &= t1 > 0.5
        at_target = cv2.remap(t1, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        ok &= at_target >= TISSUE_KEEP
    return ok.astype(np.float32)


def shrink_tissue(mask: np.ndarray) -> np.ndarray:
    """[H, W] float32 tissue mask with the tool grown by TOOL_MARGIN pixels (8-neighbourhood)."""
    tool = (mask <= 0.5).astype(np.uint8)
    if TOOL_MARGIN > 0:
        tool = cv2.dilate(tool, np.ones((2 * TOOL_MARGIN + 1,) * 2, np.uint8))
    return (1 - tool).astype(np.float32)


def training_pairs(scene):
    """[(k, k')] consecutive pairs of ``scene.train_indices``."""
    tr = list(scene.train_indices)
    return list(zip(tr[:-1], tr[1:]))


# ---------------------------------------------------------------------------------------------
def default_cache_root() -> Path:
    cache = env.get("ENDOWAVE_CL_CACHE")
    if cache:
        return Path(cache) / "flow"
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg) if xdg else Path.home() / ".cache"
    return base / "endowave-cl" / "flow"


def estimation_size(width: int, height: int, max_pixels: int = 0):
    """(w, h) at which the estimators see frames of width x height: the frame's own size, or with
    ``max_pixels`` > 0 the largest size of the same aspect with at most that many pixels."""
    if max_pixels <= 0 or width * height <= max_pixels:
        return width, height
    f = (max(max_pixels, MIN_ESTIMATION_PIXELS) / float(width * height)) ** 0.5
    return (min(width, max(MIN_ESTIMATION_SIDE, int(width * f))),
            min(height, max(MIN_ESTIMATION_SIDE, int(height * f))))


def _grey_at(image: np.ndarray, size) -> np.ndarray:
    """What the estimators see: 8-bit grey, area-averaged to ``size`` (w, h) when smaller."""
    g = to_grey8(image)
    return g if (g.shape[1], g.shape[0]) == tuple(size) else cv2.resize(g, size, interpolation=cv2.INTER_AREA)


def _to_frame_size(flow: np.ndarray, width: int, height: int) -> np.ndarray:
    """[h, w, 2] flow estimated on smaller frames -> [height, width, 2] in the frame's pixels."""
    h, w = flow.shape[:2]
    if (w, h) == (width, height):
        return flow
    out = cv2.resize(flow, (width, height), interpolation=cv2.INTER_LINEAR)
    return (out * np.array([width / w, height / h], np.float32)).astype(np.float32)



def estimate_flow_at(image0: np.ndarray, image1: np.ndarray, method: str = "dis", size=None) -> np.ndarray:
    """[H, W, 2] float32 flow from image0 to image1 as flow_for_scene estimates a training pair's:
    on 8-bit grey frames area-averaged to size ((w, h), estimation_size; None: the frames' own)
    and scaled back to the frames' size."""
    h, w = image0.shape[:2]
    size = (w, h) if size is None else tuple(size)
    raw = _estimate(_make_estimator(method), _grey_at(image0, size), _grey_at(image1, size))
    return _to_frame_size(np.asarray(raw, np.float32), w, h)

def cache_key(scene, method: str, pairs, max_pixels: int = 0) -> str:
    """SHA-256 over everything the result depends on (see the module docstring)."""
    h = hashlib.sha256()
    meta = {"version": CACHE_VERSION, "method": method, "opencv": cv2.__version__,
            "size": [scene.width, scene.height], "pairs": pairs}
    work = estimation_size(scene.width, scene.height, max_pixels)
    if work != (scene.width, scene.height):
        meta["estimated_at"] = list(work)
    h.update(json.dumps(meta).encode())
    used = sorted({i for p in pairs for i in p})
    for i in used:
        fr = scene.frames[i]
        h.update(to_grey8(fr.image).tobytes())
        h.update(b"M" + (fr.mask > 0.5).tobytes() if fr.mask is not None else b"-")
    return h.hexdigest()[:32]


def _pair_file(k, k2):
    return f"{k:06d}_{k2:06d}.npz"


def _load_cached(entry: Path, pairs):
    if not (entry / "manifest.json").is_file():
        return None
    out = {}
    for k, k2 in pairs:
        f = entry / _pair_file(k, k2)
        try:
            with np.load(f, allow_pickle=False) as z:
                p = FlowPair(k, k2, z["flow"], z["valid"].astype(np.float32),
                             z["flow_bw"], z["valid_bw"].astype(np.float32))
            hw = p.flow.shape[:2]
            if not (p.flow.ndim == 3 and p.flow.shape[2] == 2 and p.flow_bw.shape == p.flow.shape
                    and p.valid.shape == hw and p.valid_bw.shape == hw
                    and np.isfinite(p.flow).all() and np.isfinite(p.flow_bw).all()):
                raise ValueError("arrays of the wrong shape or non-finite values")
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as e:
            # damaged entry (truncated, bit-flipped): say which file, recompute and replace it
            why = getattr(e, "strerror", None) or str(e).splitlines()[0] if str(e) else type(e).__name__
            print(f"warning: flow cache file {f} is damaged ({why}); recomputing the entry", file=sys.stderr)
            return None
        out[k] = p
    return out


def _store(entry: Path, result, meta) -> bool:
    """Write the cache entry; False (with a warning naming the folder) when it cannot be written:
    the flow just computed is used all the same."""
    try:
        _store_entry(entry, result, meta)
        return True
    except OSError as e:
        print(f"warning: cannot write the flow cache in {entry.parent} ({e.strerror or e}); continuing without "
              f"caching (free space there, or choose another place with --cache-dir or ENDOWAVE_CL_CACHE)",
              file=sys.stderr)
        return False


def _store_entry(entry: Path, result, meta):
    with atomic_directory(entry, force=True) as tmp:
        for p in result.values():
            np.savez(tmp / _pair_file(p.src, p.dst), flow=p.flow, flow_bw=p.flow_bw,
                     valid=p.valid.astype(np.uint8), valid_bw=p.valid_bw.astype(np.uint8))
        (tmp / "manifest.json").write_text(json.dumps(meta, indent=2) + "\n")


# ---------------------------------------------------------------------------------------------
def _user_flow_file(folder: Path, a: str, b: str) -> Optional[Path]:
    for ext in (".npy", ".flo"):
        f = folder / f"{a}_{b}{ext}"
        if f.is_file():
            return f
    return None


def _fit_to_scene(flow, path, scene):
    """Resize user flow [h, w, 2] to the scene size, scaling the vectors with the image."""
    h, w = flow.shape[:2]
    if not np.isfinite(flow).all():
        raise DataError(f"{path}: flow contains NaN or infinite values")
    big = float(np.abs(flow).max()) if flow.size else 0.0
    if big > MAX_FLOW_FRAMES * max(w, h):
        raise DataError(f"{path}: flow vectors up to {big:.3g} pixels, beyond {MAX_FLOW_FRAMES:g}x the {w}x{h} "
                        f"frame (flow is in pixels of that frame)")
    if (h, w) == (scene.height, scene.width):
        return flow
    # the images' own size (the loader's rounding of a downscale), whatever the two ratios are
    ds = getattr(scene, "downscale", 1.0) or 1.0
    full = (int(round(w / ds)), int(round(h / ds))) == (scene.width, scene.height)
    sx, sy = scene.width / w, scene.height / h
    if not full and abs(sx - sy) > 0.02 * max(sx, sy):
        raise DataError(f"{path}: flow is {w}x{h}, which does not scale to the {scene.width}x{scene.height} frames")
    return _to_frame_size(flow, scene.width, scene.height)


def _user_flow(scene, folder: Path, pairs):
    out = SceneFlow()
    for k, k2 in pairs:
        fa, fb = scene.frames[k], scene.frames[k2]
        f_fw = _user_flow_file(folder, fa.name, fb.name)
        if f_fw is None:
            raise DataError(f"{folder}: no {fa.name}_{fb.name}.npy or .flo for the training pair "
                            f"({k}, {k2}); user flow must cover every pair")
        fw = _fit_to_scene(read_flow_file(f_fw), f_fw, scene)
        f_bw = _user_flow_file(folder, fb.name, fa.name)
        bw = _fit_to_scene(read_flow_file(f_bw), f_bw, scene) if f_bw is not None else None
        valid = valid_mask(fw, bw, fa.mask, fb.mask)
        if bw is None:
            bw = np.zeros_like(fw)
            valid_bw = np.zeros(fw.shape[:2], np.float32)      # no backward flow given: never supervise
        else:
            valid_bw = valid_mask(bw, fw, fb.mask, fa.mask)
        out[k] = FlowPair(k, k2, fw, valid, bw, valid_bw)
    out.method = "user"
    return out


def flow_for_scene(scene, method: str = "dis", cache: bool = True, progress: bool = True,
                   cache_dir=None, use_user_flow: bool = True, max_pixels: int = 0) -> SceneFlow:
    """Pseudo ground-truth flow for every consecutive pair of training frames.

    Returns ``{k: FlowPair}`` (a ``SceneFlow`` dict) with one entry per training frame k that has a
    next training frame k'.  ``method``: "dis" (default, fast), "dis_fine", "farneback",
    "deepflow" or "tvl1" (METHODS; the last two are the slowest).
    ``cache``: reuse / write the on-disk cache (module docstring);
    ``cache_dir`` overrides its root.  ``use_user_flow``: take ``<scene>/flow/`` when it has files.
    ``max_pixels`` > 0: frames larger than this many pixels are area-averaged to that size for the
    estimator (``estimation_size``) and the flow is scaled back up to the frame's size; the
    consistency masks are computed at the frame's size.
    """
    if method not in METHODS:
        raise DataError(f"unknown flow method {method!r} (choose from {', '.join(METHODS)})")
    pairs = training_pairs(scene)
    user_dir = Path(scene.path) / "flow"
    if use_user_flow and user_dir.is_dir() and any(user_dir.iterdir()):
        return _user_flow(scene, user_dir, pairs)

    entry = None
    if cache:
        entry = (Path(cache_dir) if cache_dir is not None else default_cache_root()) / cache_key(scene, method, pairs, max_pixels)
        hit = _load_cached(entry, pairs)
        if hit is not None:
            result = SceneFlow(hit)
            result.method, result.cache_path, result.computed = method, entry, False
            return result

    estimator = _make_estimator(method)
    work = estimation_size(scene.width, scene.height, max_pixels)
    grey = {i: _grey_at(scene.frames[i].image, work) for i in sorted({i for p in pairs for i in p})}
    result = SceneFlow()
    W, H = scene.width, scene.height
    for k, k2 in progress_bar(pairs, desc=f"flow ({method})", unit="pair", disable=not progress):
        fw = _to_frame_size(np.asarray(_estimate(estimator, grey[k], grey[k2]), np.float32), W, H)
        bw = _to_frame_size(np.asarray(_estimate(estimator, grey[k2], grey[k]), np.float32), W, H)
        m0, m1 = scene.frames[k].mask, scene.frames[k2].mask
        result[k] = FlowPair(k, k2, fw, valid_mask(fw, bw, m0, m1), bw, valid_mask(bw, fw, m1, m0))
    result.method, result.computed = method, True
    if cache and _store(entry, result, {"scene": str(scene.path), "method": method, "pairs": pairs,
                                        "size": [scene.width, scene.height], "estimated_at": list(work),
                                        "version": CACHE_VERSION}):
        result.cache_path = entry
    return result
