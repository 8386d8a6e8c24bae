"""A video file or a folder of frames -> a scene in the EndoNeRF layout (``endowave-cl ingest``).

What a user has is a recording, not ``images/`` plus ``poses_bounds.npy``.  ``ingest`` writes:

  images/NNNNNN.png     the chosen frames (frame range and stride), resized if asked, 8-bit RGB
  masks/NNNNNN.png      optional: tool masks from a folder, checked against the frames (255 = tool)
  depth/NNNNNN.png      optional: a depth folder checked against the frames, or with ``stereo`` the
                        depth of OpenCV's semi-global matching (uint16, value = DISPARITY_COUNTS /
                        disparity, so depth = value x depth_scale with depth_scale = f B / DISPARITY_COUNTS
                        in the baseline's units; 0 = no match)
  poses_bounds.npy      identity poses (a fixed endoscope), hwf = (H, W, f), near / far
  scene.json            depth_scale where there is depth, and "ingest": the source and the settings

Intrinsics: ``focal`` in pixels of the source frame (one eye's frame for stereo), else from a
horizontal field of view ``fov`` in degrees, else DEFAULT_FOV_DEG (a guess; the result says so).
Stereo input is assumed rectified (rows aligned, left eye first); nothing here calibrates.
The scene appears complete under OUT or not at all (atomic_directory).
"""
from __future__ import annotations

import contextlib
import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterator, List, Optional, Tuple

import cv2
import numpy as np

from ..atomic import atomic_directory, save_png, write_bytes_atomic
from ..errors import DataError
from ..progress import progress as progress_bar
from .images import _decode, list_images
from .scene import split_indices

DEFAULT_FOV_DEG = 60.0        # horizontal; EndoNeRF's pulling video has 58.6 (640 px, f = 569.5)
DEFAULT_NEAR, DEFAULT_FAR = 1.0, 100.0   # bounds without depth, in no particular unit (the loader
                                         # rescales the scene so that sqrt(near far) sits at depth 4)
DISPARITY_COUNTS = 60000.0    # stereo depth PNG value = DISPARITY_COUNTS / disparity (1 px -> 60000)
MIN_DISPARITY_PX = 1.0        # smaller disparities (farther than f B) are left invalid
STEREO_LAYOUTS = ("side-by-side", "top-bottom")


@dataclass
class IngestOptions:
    start: int = 0                     # first source frame (0-based)
    end: Optional[int] = None          # source frame to stop before (None: the end)
    stride: int = 1                    # keep every stride-th frame from start
    max_frames: Optional[int] = None   # stop after this many output frames
    width: Optional[int] = None        # output size; one of the two keeps the aspect ratio
    height: Optional[int] = None
    focal: Optional[float] = None      # pixels of the source frame (one eye)
    fov: Optional[float] = None        # horizontal field of view, degrees
    near: Optional[float] = None
    far: Optional[float] = None
    masks: Optional[str] = None        # folder of tool masks (255 = tool)
    depth: Optional[str] = None        # folder of depth maps (8/16-bit)
    depth_scale: Optional[float] = None   # file units per count of the depth folder's values
    stereo: Optional[str] = None       # "side-by-side" | "top-bottom"
    baseline: Optional[float] = None   # stereo baseline (depth comes out in its units)
    max_disparity: Optional[int] = None   # SGBM search range in output pixels (multiple of 16)
    warnings: List[str] = field(default_factory=list)


def check_options(o: IngestOptions) -> None:
    def bad(msg):
        raise DataError(msg)
    if o.start < 0:
        bad(f"--start must be >= 0, got {o.start}")
    if o.end is not None and o.end <= o.start:
        bad(f"--end ({o.end}) must be after --start ({o.start})")
    if o.stride < 1:
        bad(f"--stride must be >= 1, got {o.stride}")
    if o.max_frames is not None and o.max_frames < 2:
        bad(f"--max-frames must be at least 2 (a scene needs a training and a test frame), got {o.max_frames}")
    for name in ("width", "height"):
        v = getattr(o, name)
        if v is not None and v < 16:
            bad(f"--{name} must be at least 16 pixels, got {v}")
    if o.focal is not None and o.fov is not None:
        bad("give --focal or --fov, not both")
    if o.focal is not None and not (math.isfinite(o.focal) and o.focal > 0):
        bad(f"--focal must be a positive number of pixels, got {o.focal}")
    if o.fov is not None and not (math.isfinite(o.fov) and 0 < o.fov < 180):
        bad(f"--fov must be between 0 and 180 degrees, got {o.fov}")
    for name in ("near", "far", "baseline", "depth_scale"):
        v = getattr(o, name)
        if v is not None and not (math.isfinite(v) and v > 0):
            bad(f"--{name.replace('_', '-')} must be a positive number, got {v}")
    if o.near is not None and o.far is not None and not o.near < o.far:
        bad(f"--near ({o.near}) must be less than --far ({o.far})")
    if o.stereo is not None:
        if o.stereo not in STEREO_LAYOUTS:
            bad(f"--stereo must be one of {', '.join(STEREO_LAYOUTS)}, got {o.stereo!r}")
        if o.baseline is None:
            bad("--stereo needs --baseline (the distance between the two cameras; depth comes out in its units)")
        if o.depth is not None:
            bad("give --stereo or --depth, not both")
    elif o.baseline is not None:
        bad("--baseline needs --stereo")
    if o.max_disparity is not None and (o.max_disparity < 16 or o.max_disparity % 16):
        bad(f"--max-disparity must be a positive multiple of 16, got {o.max_disparity}")
    if o.depth_scale is not None and o.depth is None:
        bad("--depth-scale needs --depth")


# ---------------------------------------------------------------------------------------- sources
def _quiet_cv2():
    @contextlib.contextmanager
    def quiet():
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)   # we report failures ourselves
        try:
            yield
        finally:
            cv2.utils.logging.setLogLevel(level)
    return quiet()


def _quiet_ffmpeg() -> None:
    """FFmpeg's own messages (\"moov atom not found\") off: a broken video gets one line from us.
    OpenCV reads the variable when it opens a capture; a value the user set is kept."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")


def _video_frames(path: Path, o: IngestOptions) -> Iterator[Tuple[int, np.ndarray]]:
    """(source index, BGR uint8 frame) of the chosen frames of a video file."""
    _quiet_ffmpeg()
    with _quiet_cv2():
        cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise DataError(f"{path}: not a video OpenCV can open (broken, or an unsupported format)")
    reported = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    i = read = 0
    try:
        while o.end is None or i < o.end:
            with _quiet_cv2():
                ok, frame = cap.read()
            if not ok or frame is None:
                break
            read += 1
            if i >= o.start and (i - o.start) % o.stride == 0:
                yield i, frame
            i += 1
    finally:
        cap.release()
    if read == 0:
        raise DataError(f"{path}: no frame could be decoded (broken or unsupported video)")
    if o.end is None and reported > 0 and read < reported - 1:
        o.warnings.append(f"{path}: decoding stopped after {read} of the {reported} frames the file "
                          f"announces (a truncated or damaged video?)")


def _folder_frames(path: Path, o: IngestOptions) -> Iterator[Tuple[int, np.ndarray]]:
    files = list_images(path)
    if not files:
        raise DataError(f"{path}: no .png / .jpg frames in this folder")
    stop = len(files) if o.end is None else min(o.end, len(files))
    for i in range(o.start, stop, o.stride):
        img = _decode(files[i], cv2.IMREAD_UNCHANGED)
        if img.dtype == np.uint16:
            img = (img / 257.0 + 0.5).astype(np.uint8)
        elif img.dtype != np.uint8:
            raise DataError(f"{files[i]}: unsupported pixel type {img.dtype}")
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        elif img.shape[2] == 4:
            img = img[:, :, :3]
        yield i, img


def source_frames(source: Path, o: IngestOptions) -> Iterator[Tuple[int, str, np.ndarray]]:
    """(source index, what to name in an error, BGR uint8 frame), at most max_frames of them."""
    if not source.exists():
        raise DataError(f"{source}: no such file or folder")
    gen = _folder_frames(source, o) if source.is_dir() else _video_frames(source, o)
    n = 0
    for i, frame in gen:
        if o.max_frames is not None and n >= o.max_frames:
            break
        what = f"{source} (frame {i})"
        yield i, what, frame
        n += 1


def split_stereo(frame: np.ndarray, layout: str, what: str) -> Tuple[np.ndarray, np.ndarray]:
    """(left, right) halves of a side-by-side or top-bottom stereo frame."""
    h, w = frame.shape[:2]
    if layout == "side-by-side":
        if w % 2:
            raise DataError(f"{what}: a side-by-side stereo frame needs an even width, this one is {w}x{h}")
        return frame[:, : w // 2], frame[:, w // 2:]
    if h % 2:
        raise DataError(f"{what}: a top-bottom stereo frame needs an even height, this one is {w}x{h}")
    return frame[: h // 2], frame[h // 2:]


def output_size(w: int, h: int, o: IngestOptions) -> Tuple[int, int]:
    if o.width and o.height:
        return o.width, o.height
    if o.width:
        return o.width, max(1, int(round(h * o.width / w)))
    if o.height:
        return max(1, int(round(w * o.height / h))), o.height
    return w, h


def focal_pixels(w_src: int, w_out: int, o: IngestOptions) -> Tuple[float, str]:
    """Focal length in output pixels and where it came from."""
    if o.focal is not None:
        return o.focal * w_out / w_src, f"--focal {o.focal:g} px"
    fov = o.fov if o.fov is not None else DEFAULT_FOV_DEG
    f = 0.5 * w_out / math.tan(math.radians(fov) / 2)
    if o.fov is None:
        o.warnings.append(f"no --focal or --fov: assuming a {DEFAULT_FOV_DEG:g} degree horizontal field of "
                          f"view (f = {f:.1f} px), a guess; give the endoscope's calibration if you have it")
        return f, f"a guessed {fov:g} degree field of view"
    return f, f"--fov {fov:g} degrees"


# ---------------------------------------------------------------------------------------- stereo
def make_matcher(width: int, max_disparity: Optional[int]):
    """OpenCV semi-global block matching on grey frames (3-way SGBM, 5x5 blocks)."""
    nd = max_disparity or max(16, int(math.ceil(width / 4 / 16.0)) * 16)
    block = 5
    return cv2.StereoSGBM_create(minDisparity=0, numDisparities=nd, blockSize=block,
                                 P1=8 * block * block, P2=32 * block * block, disp12MaxDiff=1,
                                 uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)


def stereo_disparity(matcher, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """[H, W] float32 disparity in pixels of the left frame (<= 0: no match)."""
    gl = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY) if left.ndim == 3 else left
    gr = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY) if right.ndim == 3 else right
    return matcher.compute(gl, gr).astype(np.float32) / 16.0


def disparity_to_counts(disp: np.ndarray) -> np.ndarray:
    """uint16 depth PNG values DISPARITY_COUNTS / disparity; 0 where there is no usable disparity."""
    valid = disp >= MIN_DISPARITY_PX
    out = np.zeros(disp.shape, np.uint16)
    out[valid] = np.minimum(np.round(DISPARITY_COUNTS / disp[valid]), 65535).astype(np.uint16)
    return out


# ---------------------------------------------------------------------------------------- side folders
def _side_files(folder: Optional[str], what: str, n_source: Optional[int], chosen: List[int]):
    """Files of a masks / depth folder paired with the chosen frames: the folder holds either one
    file per chosen frame or one per source frame (then the same frames are taken)."""
    if folder is None:
        return None
    p = Path(folder)
    if not p.is_dir():
        raise DataError(f"{p}: the {what} folder does not exist")
    files = list_images(p)
    if len(files) == len(chosen):
        return files
    if n_source is not None and len(files) == n_source:
        return [files[i] for i in chosen]
    raise DataError(f"{p}: {len(files)} {what} files, but {len(chosen)} frames are taken"
                    + (f" from {n_source}" if n_source is not None else "")
                    + " (one file per taken frame, or one per source frame, in name order)")


def _read_side(path: Path, src_size, out_size, what: str) -> np.ndarray:
    img = _decode(path, cv2.IMREAD_UNCHANGED)
    if img.ndim == 3:
        img = img[:, :, :3].max(axis=2) if what == "mask" else img[:, :, 0]
    h, w = img.shape[:2]
    if (w, h) == tuple(out_size):
        return img
    if (w, h) != tuple(src_size):
        raise DataError(f"{path}: {what} size {w}x{h} matches neither the frames ({src_size[0]}x{src_size[1]}) "
                        f"nor the output ({out_size[0]}x{out_size[1]})")
    return cv2.resize(img, tuple(out_size), interpolation=cv2.INTER_NEAREST)


# ---------------------------------------------------------------------------------------- the scene
@dataclass
class IngestResult:
    out: Path
    frames: int
    width: int
    height: int
    focal: float
    focal_source: str
    train: List[int]
    test: List[int]
    has_depth: bool
    has_masks: bool
    warnings: List[str]


def _count_source_frames(source: Path) -> Optional[int]:
    """Frames in the source: the folder's image count, or the count a video announces (None if not)."""
    if source.is_dir():
        return len(list_images(source))
    _quiet_ffmpeg()
    with _quiet_cv2():
        cap = cv2.VideoCapture(str(source))
    try:
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0) if cap.isOpened() else 0
    finally:
        cap.release()
    return n if n > 0 else None


def ingest(source, out, options: Optional[IngestOptions] = None, force: bool = False,
           log=print, progress: bool = True) -> IngestResult:
    """Write the EndoNeRF-layout scene of ``source`` (a video file or a folder of frames) to ``out``."""
    o = options or IngestOptions()
    check_options(o)
    source, out = Path(source), Path(out)
    if out.resolve() == source.resolve():
        raise DataError(f"{out}: the output folder cannot be the source")
    if out.exists() and not out.is_dir():
        raise DataError(f"{out}: exists and is not a folder")
    n_source = _count_source_frames(source) if (o.masks or o.depth) else None
    masks_dir = Path(o.masks) if o.masks else None
    depth_dir = Path(o.depth) if o.depth else None
    with atomic_directory(out, force=force) as tmp:
        (tmp / "images").mkdir()
        chosen: List[int] = []
        src_size = size = None
        focal = None
        focal_from = ""
        matcher = None
        near_far_depths: List[float] = []
        bar = progress_bar(desc="ingest", unit="frame", disable=not progress)
        for i, what, frame in source_frames(source, o):
            right = None
            if o.stereo:
                frame, right = split_stereo(frame, o.stereo, what)
            h, w = frame.shape[:2]
            if src_size is None:
                src_size = (w, h)
                size = output_size(w, h, o)
                focal, focal_from = focal_pixels(w, size[0], o)
                if o.stereo:
                    matcher = make_matcher(size[0], o.max_disparity)
            elif (w, h) != src_size:
                raise DataError(f"{what}: size {w}x{h} differs from the first frame's {src_size[0]}x{src_size[1]}")
            k = len(chosen)
            name = f"{k:06d}.png"
            if size != src_size:
                interp = cv2.INTER_AREA if size[0] < w else cv2.INTER_LINEAR
                frame = cv2.resize(frame, size, interpolation=interp)
                if right is not None:
                    right = cv2.resize(right, size, interpolation=interp)
            save_png(tmp / "images" / name, frame, atomic=False)
            if right is not None:
                counts = disparity_to_counts(stereo_disparity(matcher, frame, right))
                (tmp / "depth").mkdir(exist_ok=True)
                save_png(tmp / "depth" / name, counts, atomic=False)
                v = counts[counts > 0]
                if v.size:
                    near_far_depths += [float(v.min()), float(v.max())]
            chosen.append(i)
            bar.update(1)
        bar.close()
        if len(chosen) < 2:
            raise DataError(f"{source}: {len(chosen)} frame(s) taken (range {o.start}..{o.end if o.end is not None else 'end'}, "
                            f"stride {o.stride}); a scene needs at least 2")
        wo, ho = size
        depth_scale = None
        has_masks, has_depth = False, o.stereo is not None
        mfiles = _side_files(o.masks, "mask", n_source, chosen)
        if mfiles is not None:
            (tmp / "masks").mkdir()
            for k, p in enumerate(mfiles):
                m = _read_side(p, src_size, size, "mask")
                half = (np.iinfo(m.dtype).max + 1) // 2 if m.dtype.kind in "ui" else 0.5
                save_png(tmp / "masks" / f"{k:06d}.png", np.where(m >= half, 255, 0).astype(np.uint8), atomic=False)
            has_masks = True
        dfiles = _side_files(o.depth, "depth", n_source, chosen)
        if dfiles is not None:
            (tmp / "depth").mkdir()
            for k, p in enumerate(dfiles):
                d = _read_side(p, src_size, size, "depth")
                if d.dtype not in (np.uint8, np.uint16):
                    raise DataError(f"{p}: depth must be 8- or 16-bit, got {d.dtype}")
                save_png(tmp / "depth" / f"{k:06d}.png", d, atomic=False)
                v = d[d > 0]
                if v.size:
                    near_far_depths += [float(v.min()), float(v.max())]
            depth_scale = o.depth_scale
            has_depth = True
        if o.stereo:
            depth_scale = focal * o.baseline / DISPARITY_COUNTS
            if not near_far_depths:
                o.warnings.append("stereo matching found no disparity in any frame: check --stereo and the "
                                  "eye order (left first); the depth folder has no valid pixel")
        # bounds: from the depth (0.9 x nearest, 1.1 x farthest) unless given
        scale = depth_scale or 1.0
        if near_far_depths:
            near = o.near if o.near is not None else 0.9 * min(near_far_depths) * scale
            far = o.far if o.far is not None else 1.1 * max(near_far_depths) * scale
        else:
            near = o.near if o.near is not None else DEFAULT_NEAR
            far = o.far if o.far is not None else max(DEFAULT_FAR, 10 * near)
        if not near < far:
            raise DataError(f"near bound {near:g} is not below far bound {far:g}: check --near / --far")
        pose = np.concatenate([np.eye(3), np.zeros((3, 1)), np.array([[ho], [wo], [focal]])], axis=1)
        pb = np.tile(np.concatenate([pose.reshape(-1), [near, far]])[None], (len(chosen), 1))
        with open(tmp / "poses_bounds.npy", "wb") as f:
            np.save(f, pb.astype(np.float64))
        info = {"hwf_layout": "hwf",
                "ingest": {"source": str(source.resolve()), "source_frames": chosen, "size": [wo, ho],
                           "focal_px": focal, "focal_from": focal_from,
                           "options": {k: v for k, v in asdict(o).items() if k != "warnings" and v is not None},
                           "stereo_note": ("depth from OpenCV semi-global matching, rectified input assumed; "
                                           "depth = depth_scale x value in the baseline's units")
                           if o.stereo else None}}
        if depth_scale is not None:
            info["depth_scale"] = depth_scale
        write_bytes_atomic(tmp / "scene.json", json.dumps(info, indent=1).encode())
    train, test = split_indices(len(chosen))
    return IngestResult(out, len(chosen), wo, ho, focal, focal_from, train, test, has_depth, has_masks,
                        list(o.warnings))


def describe_split(train: List[int], test: List[int]) -> str:
    shown = ", ".join(str(i) for i in test[:6]) + (", ..." if len(test) > 6 else "")
    return (f"{len(train)} training / {len(test)} test frames (test frames: (i - 1) % 8 == 0, "
            f"i.e. {shown})")
