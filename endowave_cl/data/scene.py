"""Loader for scenes in the EndoNeRF layout (see docs/DATA.md).

::

    scene/
      images/*.png        RGB frames, sorted by name = frame order
      depth/*.png         optional, raw 8/16-bit depth, 0 = invalid
      masks/*.png         optional, 255 = tool (returned inverted: 1 = tissue to supervise)
      poses_bounds.npy    [N, 17]: LLFF pose 3x5 [R | t | hwf] per frame, then near, far
      scene.json          optional: {"depth_scale": scene units per raw depth count,
                                     "hwf_layout": "hwf" | "cy_cx_f"}

Frames of the three folders are paired by sorted order and their counts must agree.
"""
from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

import cv2
import numpy as np

from ..camera import Camera
from ..errors import DataError
from .images import list_images, read_depth_raw, read_rgb, read_tissue_mask
from .llff import HWF_LAYOUTS, intrinsics_from_hwf, llff_to_viewmat, read_poses_bounds

# EndoNeRF-style loaders (EndoNeRF, Deform3DGS) clip each depth map to these percentiles of its
# valid pixels to drop stereo-matching outliers.
DEFAULT_DEPTH_PERCENTILES = (3.0, 99.8)
# scene.json depth_scale (scene units per raw depth count): values outside this range are unit
# mistakes, and their products with 16-bit counts leave float32 (0 or inf)
DEPTH_SCALE_RANGE = (1e-9, 1e9)
# Every TEST_EVERY-th frame starting at frame 1 is a test frame: (i - 1) % 8 == 0.
TEST_EVERY = 8
# The validation split (for choosing settings without reading a test frame): the training frames
# at VALIDATION_OFFSET, midway between two test frames, at the test frames' spacing:
# (i - 5) % 8 == 0.  Like a test frame, each has training frames at i - 1 and i + 1.
VALIDATION_OFFSET = 5
# what a run is trained on and scored at (TrainConfig.split): "test" trains on every non-test frame
# and scores the test frames; "validation" also holds the validation frames out and scores them
SPLITS = ("test", "validation")
# camera centres this close (relative to the far bound) count as one viewpoint (Scene.one_viewpoint)
VIEWPOINT_TOL = 1e-6
# A downscaled mask pixel counts as tissue only if all full-size pixels under it were tissue
# (area-averaged value at least this).
MASK_KEEP = 0.999
# Scene units.  A 4D Gaussian moves by turning in the space-time planes, and how far it must turn
# for a given image motion depends on how space is measured against time (time is [0, 1] over the
# sequence): the same scene in other depth units trains differently (research/QUALITY.md, finding 18).
# So the loader measures space in units that put the scene's typical depth at SCENE_DEPTH: the
# median valid depth of the training frames, or without depth maps the depth-free prior plane
# (PRIOR_NEAR_FLOOR below).  4 is the depth the defaults were validated at (the synthetic scenes'
# tissue lies at 2-6 units, the prior plane of the real pulling frames at 3.8).
SCENE_DEPTH = 4.0
# The depth-free prior plane sits at sqrt(near * far), the bounds' midpoint in log-depth; a near
# bound of 0 carries no scale and is replaced by far * PRIOR_NEAR_FLOOR.
PRIOR_NEAR_FLOOR = 1e-3


@dataclass
class Frame:
    index: int                     # position in the sequence, 0..N-1
    time: float                    # index / (N - 1), in [0, 1]
    image: np.ndarray              # [H, W, 3] float32 RGB in [0, 1]
    depth: Optional[np.ndarray]    # [H, W] float32 in scene units (Scene.world_scale), 0 = invalid
    mask: Optional[np.ndarray]     # [H, W] float32, 1 = tissue to supervise, 0 = tool
    camera: Camera                 # OpenCV convention, world -> camera viewmat
    name: str = ""                 # stem of the image file, e.g. "000012"


@dataclass
class Scene:
    path: Path
    frames: List[Frame]
    train_indices: List[int]
    test_indices: List[int]
    near: float                    # min of the near bounds in poses_bounds.npy (scene units)
    far: float                     # max of the far bounds (scene units)
    width: int
    height: int
    has_depth: bool
    has_masks: bool
    downscale: float = 1.0
    depth_scale: Optional[float] = None   # from scene.json; None = depth in raw file units
    hwf_layout: str = "hwf"
    info: dict = field(default_factory=dict)   # scene.json content
    world_scale: float = 1.0       # scene units per file unit (depth after depth_scale, pose translations, bounds)
    split: str = "test"            # which frames test_indices holds (apply_split): "test" or "validation"

    def summary(self) -> str:
        """One line: what was found and what the trainer will do with it."""
        n = len(self.frames)
        parts = [f"{n} frames", f"{self.width}x{self.height}"]
        if self.downscale != 1:
            parts[-1] += f" (downscale {self.downscale:g})"
        parts.append("depth" if self.has_depth else "no depth")
        parts.append("masks" if self.has_masks else "no masks")
        effects = ["depth loss " + ("on" if self.has_depth else "off")]
        effects.append("tool pixels excluded" if self.has_masks else "every pixel supervised")
        split = f"{len(self.train_indices)} train / {len(self.test_indices)} {self.split}"
        return (f"{', '.join(parts)}: {', '.join(effects)}; {split}; scene units = file units x "
                f"{self.world_scale:.4g}")

    def set_world_scale(self, world_scale: float) -> None:
        """Measure the scene in other units, in place: depth maps, camera translations and bounds
        are multiplied by world_scale / self.world_scale (a run trained in other units is
        evaluated or resumed in its own)."""
        world_scale = float(world_scale)
        if not (np.isfinite(world_scale) and world_scale > 0):
            raise DataError(f"{self.path}: world_scale must be a positive number, got {world_scale!r}")
        r = world_scale / self.world_scale
        if r == 1.0:
            return
        for f in self.frames:
            if f.depth is not None:
                f.depth = f.depth * np.float32(r)   # float32
            f.camera = _rescaled_camera(f.camera, r)
        self.near, self.far = self.near * r, self.far * r
        self.world_scale = world_scale

    def one_viewpoint(self) -> bool:
        """Whether every training frame's camera centre is the same point (a fixed endoscope), to
        within VIEWPOINT_TOL of the far bound."""
        centres = np.stack([self.frames[i].camera.campos.astype(np.float64) for i in self.train_indices] or
                           [np.zeros(3)])                                                        # [N, 3]
        return float(np.ptp(centres, axis=0).max()) <= VIEWPOINT_TOL * max(1.0, abs(self.far))


def check_supervised(scene, scored: str = "test") -> None:
    """Refuse masks that leave nothing to train or score, before any work: every scored frame needs
    a tissue pixel (PSNR and SSIM are taken over tissue), and some training frame needs one."""
    if not scene.has_masks:
        return
    files = list_images(Path(scene.path) / "masks")
    where = f" (downscale {scene.downscale:g})" if scene.downscale != 1 else ""
    for i in scene.test_indices:
        if not np.any(scene.frames[i].mask > 0.5):
            raise DataError(f"{files[i] if i < len(files) else scene.path}: the mask of {scored} frame {i} is all tool"
                            f"{where}: no tissue pixel to score it on")
    if scene.train_indices and not any(np.any(scene.frames[i].mask > 0.5) for i in scene.train_indices):
        raise DataError(f"{Path(scene.path) / 'masks'}: every training frame's mask is all tool{where}: no "
                        f"tissue pixel to train on")


def split_indices(n: int, test_every: int = TEST_EVERY):
    """EndoNeRF split: frames with (i - 1) % test_every == 0 are test frames, the rest train."""
    test = [i for i in range(n) if (i - 1) % test_every == 0]
    train = [i for i in range(n) if (i - 1) % test_every != 0]
    return train, test


def validation_indices(n: int, test_every: int = TEST_EVERY) -> List[int]:
    """The validation frames of an n-frame sequence: (i - VALIDATION_OFFSET) % test_every == 0,
    never a test frame, never the first or last frame (each has a neighbour on both sides)."""
    test = set(split_indices(n, test_every)[1])
    return [i for i in range(1, n - 1) if (i - VALIDATION_OFFSET) % test_every == 0 and i not in test]


def apply_split(scene: "Scene", split: str) -> "Scene":
    """The scene as a run with this split trains and scores it (SPLITS), in place: "test" leaves it
    as loaded; "validation" moves the validation frames out of the training frames and makes them
    the scored frames, so that nothing trained or scored is a test frame.  Returns the scene."""
    if split not in SPLITS:
        raise DataError(f"split must be one of {', '.join(SPLITS)}, got {split!r}")
    if split == "validation":
        val = validation_indices(len(scene.frames))
        held = set(val)
        scene.train_indices = [i for i in scene.train_indices if i not in held]
        scene.test_indices = val
        scene.split = split
    return scene


def _read_scene_json(path: Path) -> dict:
    f = path / "scene.json"
    if not f.is_file():
        return {}
    try:
        info = json.loads(f.read_text())
    except (OSError, ValueError) as e:
        raise DataError(f"{f}: not valid JSON ({e})") from None
    if not isinstance(info, dict):
        raise DataError(f"{f}: expected a JSON object")
    if "depth_scale" in info:
        s = info["depth_scale"]
        lo, hi = DEPTH_SCALE_RANGE
        if isinstance(s, bool) or not isinstance(s, (int, float)) or not (lo <= s <= hi):
            raise DataError(f"{f}: depth_scale must be a positive number from {lo:g} to {hi:g} (scene units per "
                            f"raw depth count), got {s!r}")
    if "hwf_layout" in info and info["hwf_layout"] not in HWF_LAYOUTS[1:]:
        raise DataError(f"{f}: hwf_layout must be one of {HWF_LAYOUTS[1:]}, got {info['hwf_layout']!r}")
    return info


def _optional_files(folder: Path, n: int, what: str):
    if not folder.is_dir():
        return None
    files = list_images(folder)
    if not files:
        return None
    if len(files) != n:
        raise DataError(f"{folder}: {len(files)} {what} files but {n} images (frame count mismatch)")
    return files


def _check_size(arr: np.ndarray, path: Path, width: int, height: int, of: str = "the images"):
    if arr.shape[:2] != (height, width):
        raise DataError(f"{path}: size {arr.shape[1]}x{arr.shape[0]} disagrees with the "
                        f"{width}x{height} of {of}")


def _png_size(path: Path):
    """(width, height) from a PNG's IHDR chunk without decoding it; None if not a readable PNG."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError:
        return None
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def _common_size(images) -> tuple:
    """(width, height) most of the images have (ties: the earliest), so that an odd one out is
    blamed whichever frame it is, the first included.  PNG sizes come from the header; other
    files (or damaged headers) are decoded."""
    sizes = []
    for p in images:
        size = _png_size(p)
        sizes.append(size if size is not None else read_rgb(p).shape[1::-1])
    counts = Counter(sizes)
    return max(sizes, key=lambda s: (counts[s], -sizes.index(s)))


def clip_depth(depth: np.ndarray, percentiles) -> np.ndarray:
    """Clip valid (> 0) depth to the given percentiles of its valid values; 0 stays 0 (invalid)."""
    if percentiles is None:
        return depth
    lo_p, hi_p = percentiles
    valid = depth > 0
    lo, hi = np.percentile(depth[valid], [lo_p, hi_p])
    out = np.where(valid, np.clip(depth, lo, hi), 0.0)
    return out.astype(np.float32)


def _rescaled_camera(camera: Camera, r: float) -> Camera:
    """The camera of a world whose coordinates are multiplied by r (translation x r)."""
    V = camera.viewmat.astype(np.float64).copy()
    V[:3, 3] *= r
    return Camera(camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, V, camera.near)


def prior_plane_depth(near: float, far: float) -> float:
    """Depth of the fronto-parallel prior surface of a scene without depth maps: sqrt(near * far)
    with a near bound of 0 replaced by far * PRIOR_NEAR_FLOOR (scale-free: the arithmetic midpoint
    would sit far behind the tissue)."""
    return float(np.sqrt(max(near, far * PRIOR_NEAR_FLOOR) * far))


def unit_world_scale(depth_maps, near: float, far: float) -> float:
    """The world_scale that puts the scene's typical depth at SCENE_DEPTH: the median of the valid
    (> 0) values of depth_maps (the training frames', in file units), or without any the prior
    plane's depth from the bounds."""
    vals = [np.asarray(d)[np.asarray(d) > 0] for d in depth_maps if d is not None]
    vals = [v for v in vals if v.size]
    ref = float(np.median(np.concatenate(vals))) if vals else prior_plane_depth(near, far)
    return SCENE_DEPTH / ref if ref > 0 and np.isfinite(ref) else 1.0


def _downscaled_size(width, height, downscale):
    return int(round(width / downscale)), int(round(height / downscale))


def load_scene(path, downscale: float = 1, depth_percentiles=DEFAULT_DEPTH_PERCENTILES,
               hwf_layout: str = "auto", use_depth: bool = True, use_masks: bool = True,
               test_every: int = TEST_EVERY, world_scale: Optional[float] = None) -> Scene:
    """Load an EndoNeRF-layout scene.

    path:              the scene folder (images/, poses_bounds.npy, optional depth/, masks/, scene.json).
    downscale:         factor >= 1; images are area-averaged, depth is resampled nearest (so no
                       invalid 0 is mixed in), a mask pixel stays tissue only if fully tissue;
                       intrinsics are divided by the factor.
    depth_percentiles: (lo, hi) percentiles each depth map's valid pixels are clipped to, or None.
    hwf_layout:        "auto" (scene.json "hwf_layout" if present, else detected, see llff.py),
                       "hwf" (EndoNeRF) or "cy_cx_f" (StereoMIS conversions).
    use_depth/use_masks: ignore depth/ or masks/ even when present.
    world_scale:       scene units per file unit; None: unit_world_scale (the median depth of the
                       training frames at SCENE_DEPTH, measured on the depth maps at full size,
                       read for it even with use_depth=False, so that every use of a scene agrees).
    Raises DataError naming the file for missing poses, frame-count mismatches, unreadable or
    truncated images, sizes that disagree, and depth maps with no valid pixel.
    """
    path = Path(path)
    if not path.is_dir():
        raise DataError(f"{path}: scene folder not found")
    if not downscale >= 1:
        raise DataError(f"{path}: downscale must be >= 1, got {downscale}")
    info = _read_scene_json(path)
    img_dir = path / "images"
    if not img_dir.is_dir():
        raise DataError(f"{img_dir}: missing (the scene needs an images/ folder)")
    images = list_images(img_dir)
    if not images:
        raise DataError(f"{img_dir}: no .png/.jpg images")
    poses = read_poses_bounds(path / "poses_bounds.npy")
    n = len(images)
    if poses.shape[0] != n:
        raise DataError(f"{path / 'poses_bounds.npy'}: {poses.shape[0]} poses but {n} images in "
                        f"{img_dir} (frame count mismatch)")
    all_depth_files = _optional_files(path / "depth", n, "depth")
    depth_files = all_depth_files if use_depth else None
    mask_files = _optional_files(path / "masks", n, "mask") if use_masks else None
    depth_scale = info.get("depth_scale")

    near = float(poses[:, 15].min())
    far = float(poses[:, 16].max())
    if not (far > near >= 0):
        raise DataError(f"{path / 'poses_bounds.npy'}: bounds near={near:g}, far={far:g} are not "
                        f"0 <= near < far")

    layout = hwf_layout
    if layout == "auto" and "hwf_layout" in info:
        layout = info["hwf_layout"]

    # the size most images share is the scene's: an image of another size is named (whichever
    # frame it is) rather than the first depth map or mask compared with it
    width, height = _common_size(images)
    train, test = split_indices(n, test_every)
    train_set = set(train)
    frames, full_depth = [], {}   # full_depth: the training frames' depth maps at full size
    resolved_layout = None
    for i, img_path in enumerate(images):
        image = read_rgb(img_path)
        _check_size(image, img_path, width, height, "the other images" if n > 1 else "the images")
        depth = mask = None
        if depth_files is not None:
            depth = _read_depth(depth_files[i], width, height, depth_scale, depth_percentiles)
            if i in train_set:
                full_depth[i] = depth
        if mask_files is not None:
            mask = read_tissue_mask(mask_files[i])
            _check_size(mask, mask_files[i], width, height)

        src = f"{path / 'poses_bounds.npy'} (row {i})"
        pose = poses[i, :15].reshape(3, 5)
        fx, fy, cx, cy = intrinsics_from_hwf(pose[:, 4], width, height, layout, src)
        if resolved_layout is None:
            a, b = pose[0, 4], pose[1, 4]
            resolved_layout = layout if layout != "auto" else (
                "hwf" if (round(a), round(b)) == (height, width) else "cy_cx_f")
        camera = Camera(fx, fy, cx, cy, width, height, llff_to_viewmat(pose[:, :4]))

        if downscale != 1:
            w2, h2 = _downscaled_size(width, height, downscale)
            image = cv2.resize(image, (w2, h2), interpolation=cv2.INTER_AREA)
            if depth is not None:
                depth = cv2.resize(depth, (w2, h2), interpolation=cv2.INTER_NEAREST)
            if mask is not None:
                mask = (cv2.resize(mask, (w2, h2), interpolation=cv2.INTER_AREA) >= MASK_KEEP
                        ).astype(np.float32)
            camera = camera.scaled(downscale)
        frames.append(Frame(index=i, time=i / (n - 1) if n > 1 else 0.0, image=image, depth=depth,
                            mask=mask, camera=camera, name=img_path.stem))

    scene = Scene(path=path, frames=frames, train_indices=train, test_indices=test, near=near,
                  far=far, width=frames[0].camera.width, height=frames[0].camera.height,
                  has_depth=depth_files is not None, has_masks=mask_files is not None,
                  downscale=float(downscale), depth_scale=depth_scale, hwf_layout=resolved_layout,
                  info=info)
    if world_scale is None:
        maps = [full_depth[i] if i in full_depth else
                _read_depth(all_depth_files[i], width, height, depth_scale, depth_percentiles)
                for i in train] if all_depth_files is not None else []
        world_scale = unit_world_scale(maps, near, far)
    scene.set_world_scale(world_scale)
    return scene


def _read_depth(file: Path, width: int, height: int, depth_scale, depth_percentiles) -> np.ndarray:
    """One depth map in file units (times depth_scale), its valid values clipped to the percentiles."""
    depth = read_depth_raw(file)
    _check_size(depth, file, width, height)
    if not np.any(depth > 0):
        raise DataError(f"{file}: depth map has no valid (non-zero) pixel")
    if depth_scale is not None:
        raw = depth
        with np.errstate(over="ignore", under="ignore"):
            depth = depth * np.float32(depth_scale)
        lost = (raw > 0) & ~(np.isfinite(depth) & (depth > 0))
        if lost.any():
            raise DataError(f"{file}: depth_scale {depth_scale:g} (scene.json) takes raw depth {float(raw[lost][0]):g} "
                            f"to {float(depth[lost][0]):g}, outside float32; check the scale")
    return clip_depth(depth, depth_percentiles)
