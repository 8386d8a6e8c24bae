"""What the viewer shows, independent of the web front end (endowave_cl/viewer_app.py holds the
viser wiring): browser camera -> our Camera, the rendered views (colour, colour-mapped depth, flow on
a colour wheel), the ground-truth / error / tool-mask panes at frame times, their composition into
the one image that is streamed (a 2 x 2 grid when any is on), the 3D Gaussians at a time for the
browser's splat renderer, and the gentle orbit around a frame camera (gentle_pose).

Everything here is plain numpy + the OpenCL render op, so it is tested without a browser.
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import cv2
import numpy as np

from .camera import Camera
from .export_ply import matrix_to_quaternion
from .gaussians import MARGINAL_CULL, TEASH_PERIOD, covariance_4d, sh_basis_terms, upload
from .render import render

MODES = ("colour", "depth", "flow")   # what the main pane shows
DEPTH_PERCENTILES = (2.0, 98.0)       # the depth colour map spans these percentiles of the first depth view
FLOW_PERCENTILE = 99.0                # the flow wheel saturates at this percentile of the first flow view ...
FLOW_MIN_SCALE = 1e-3                 # ... but never below this fraction of the image height
ALPHA_EMPTY = 0.5                     # depth / flow of pixels with less accumulated opacity are shown black
ERROR_FULL_SCALE = 0.25               # error pane saturates here: the same scale as eval_worst.png
PANE_GAP = 4                          # pixels of background between the panes
# The gentle orbit (gentle_pose).  viser's orbit controls turn the browser camera by
# 2 pi * drag / canvas height radians (camera-controls' rotate speed 1, not settable from the server):
# 120 px on an 800 px canvas = 54 degrees, a grazing side view of tissue seen head-on.  The server
# renderer therefore renders from the browser camera's rotation away from the frame camera scaled by
# ORBIT_SENSITIVITY and clamped at ORBIT_MAX_DEG: 120 px on 800 px -> 13.5 degrees, the limit at
# 267 px; a 120 px drag turns the view at most ORBIT_MAX_DEG on any canvas.  Pan and zoom are kept.
ORBIT_SENSITIVITY = 0.25
ORBIT_MAX_DEG = 30.0


# ---------------------------------------------------------------------------------------------
# cameras

def quat_to_matrix(wxyz) -> np.ndarray:
    """Unit quaternion (w, x, y, z) -> [3, 3] rotation matrix."""
    w, x, y, z = (float(v) for v in np.asarray(wxyz, np.float64) / np.linalg.norm(wxyz))
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_to_quat(R) -> np.ndarray:
    """[3, 3] rotation matrix -> unit quaternion (w, x, y, z), w >= 0."""
    q = matrix_to_quaternion(np.asarray(R, np.float64)[None])[0]
    return q if q[0] >= 0 else -q


def camera_from_pose(wxyz, position, fov_y: float, width: int, height: int, near: float = 0.01) -> Camera:
    """A browser camera -> our pinhole Camera of ``width`` x ``height`` pixels.

    viser reports the camera-to-world rotation (wxyz) and the centre (position) in the OpenCV
    convention our Camera uses (x right, y down, z forward) and a vertical field of view; the
    principal point is the image centre and pixels are square."""
    R = quat_to_matrix(wxyz)                        # camera -> world
    p = np.asarray(position, np.float64).reshape(3)
    view = np.eye(4)
    view[:3, :3] = R.T
    view[:3, 3] = -R.T @ p
    fy = 0.5 * height / math.tan(0.5 * float(fov_y))
    return Camera(fy, fy, 0.5 * width, 0.5 * height, int(width), int(height), view.astype(np.float32), near)


def pose_of_camera(cam: Camera) -> Tuple[np.ndarray, np.ndarray, float]:
    """Our Camera -> (wxyz, position, vertical fov in radians): what the browser starts from."""
    R = cam.viewmat[:3, :3].astype(np.float64)
    return matrix_to_quat(R.T), cam.campos.astype(np.float64), 2.0 * math.atan(0.5 * cam.height / cam.fy)


def _axis_angle(R: np.ndarray) -> Tuple[np.ndarray, float]:
    """Rotation matrix -> (unit axis, angle in radians, 0..pi)."""
    R = np.asarray(R, np.float64)
    c = float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    ang = math.acos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    n = float(np.linalg.norm(v))
    if n > 1e-9:
        return v / n, ang
    if ang < 1e-6:
        return np.array([0.0, 0.0, 1.0]), 0.0
    # angle ~ pi: the axis is the column of R + I with the largest norm
    B = R + np.eye(3)
    col = B[:, int(np.argmax(np.linalg.norm(B, axis=0)))]
    return col / np.linalg.norm(col), ang


def _rotation(axis: np.ndarray, ang: float) -> np.ndarray:
    """Rodrigues: rotation by ``ang`` radians about the unit ``axis``."""
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], np.float64)
    return np.eye(3) + math.sin(ang) * K + (1.0 - math.cos(ang)) * K @ K


@dataclass
class GentlePose:
    wxyz: np.ndarray            # the camera the view is rendered from: camera -> world rotation
    position: np.ndarray        # ... and its centre
    raw_deg: float              # how far the browser camera has turned from the frame camera
    deg: float                  # how far the rendered view has turned (<= max_deg)
    limit_position: Optional[np.ndarray]   # where to pull the browser camera back to (None: no need)


def gentle_pose(wxyz, position, look_at, home_wxyz, sensitivity: float = ORBIT_SENSITIVITY,
                max_deg: float = ORBIT_MAX_DEG, slack_deg: float = 1.0) -> GentlePose:
    """The camera to render from for a browser camera (wxyz, position) orbiting ``look_at``, given
    the frame camera's rotation ``home_wxyz`` the orbit started from.

    The browser camera's rotation away from the frame camera (axis, angle) is scaled by
    ``sensitivity`` and clamped at ``max_deg``; the rendered camera has that rotation and keeps the
    browser's orbit point and distance, so pan and zoom pass through unchanged.  Once the browser
    camera has turned past max_deg / sensitivity (+ ``slack_deg``), nothing more would change on
    screen: ``limit_position`` is then the browser camera's centre at exactly that angle (same orbit
    point and distance), for the app to pull the browser back to, so turning back answers at once.
    sensitivity 1 and max_deg 180 give the browser camera itself."""
    R_b = quat_to_matrix(wxyz)
    R_h = quat_to_matrix(home_wxyz)
    p = np.asarray(position, np.float64).reshape(3)
    target = np.asarray(look_at, np.float64).reshape(3)
    dist = float(np.linalg.norm(target - p))
    axis, ang = _axis_angle(R_b @ R_h.T)
    raw = math.degrees(ang)
    deg = min(raw * sensitivity, max_deg)
    R_r = _rotation(axis, math.radians(deg)) @ R_h
    if dist > 0:
        pos_r = target - dist * R_r[:, 2]
    else:                                     # no orbit point: turn in place
        pos_r = p
    limit = None
    lim_deg = max_deg / max(sensitivity, 1e-9)
    if dist > 0 and raw > lim_deg + slack_deg and lim_deg < 180.0:
        R_l = _rotation(axis, math.radians(lim_deg)) @ R_h
        limit = target - dist * R_l[:, 2]
    return GentlePose(matrix_to_quat(R_r), pos_r, raw, deg, limit)


def render_size(height: int, aspect: float) -> Tuple[int, int]:
    """(width, height) of a render ``height`` pixels high at the browser canvas's aspect (w / h)."""
    h = max(8, int(height))
    a = aspect if math.isfinite(aspect) and aspect > 0 else 1.0
    return max(8, int(round(h * a))), h


# ---------------------------------------------------------------------------------------------
# colour maps

def _to_u8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)


def depth_image(depth: np.ndarray, alpha: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Expected depth (depth / alpha) through the turbo colour map, near = red end, far = blue end;
    pixels the Gaussians hardly cover are black.  uint8 RGB [H, W, 3]."""
    d = depth / np.maximum(alpha, 1e-6)
    s = np.clip((hi - d) / max(hi - lo, 1e-12), 0.0, 1.0)            # 1 = near
    rgb = cv2.applyColorMap((s * 255 + 0.5).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    return np.where((alpha >= ALPHA_EMPTY)[..., None], rgb, 0).astype(np.uint8)


def depth_range(depth: np.ndarray, alpha: np.ndarray) -> Tuple[float, float]:
    """The depth colour map's range: DEPTH_PERCENTILES of the covered pixels' expected depth."""
    ok = alpha >= ALPHA_EMPTY
    if not ok.any():
        return 0.0, 1.0
    d = (depth / np.maximum(alpha, 1e-6))[ok]
    lo, hi = np.percentile(d, DEPTH_PERCENTILES)
    return float(lo), float(max(hi, lo + 1e-6))


def flow_image(flow: np.ndarray, alpha: np.ndarray, scale: float) -> np.ndarray:
    """Flow [H, W, 2] in pixels on the usual colour wheel: hue = direction, saturation = magnitude
    / scale (white = still, saturated at ``scale`` pixels); uncovered pixels black.  uint8 RGB."""
    mag = np.hypot(flow[..., 0], flow[..., 1])
    ang = (np.degrees(np.arctan2(flow[..., 1], flow[..., 0])) % 360.0) / 2.0     # OpenCV hue: 0..180
    hsv = np.stack([ang, np.clip(mag / max(scale, 1e-12), 0, 1) * 255, np.full_like(mag, 255)], -1)
    rgb = cv2.cvtColor(hsv.astype(np.uint8), cv2.COLOR_HSV2RGB)
    return np.where((alpha >= ALPHA_EMPTY)[..., None], rgb, 0).astype(np.uint8)


def error_image(pred: np.ndarray, gt: np.ndarray, mask: Optional[np.ndarray]) -> np.ndarray:
    """Mean |render - ground truth| over RGB through the inferno map, saturating at
    ERROR_FULL_SCALE; tool pixels (mask 0) count as 0, as eval scores them.  uint8 RGB."""
    err = np.abs(np.clip(pred, 0, 1) - gt).mean(-1)
    if mask is not None:
        err = err * mask
    e8 = np.clip(err / ERROR_FULL_SCALE * 255 + 0.5, 0, 255).astype(np.uint8)
    return cv2.applyColorMap(e8, cv2.COLORMAP_INFERNO)[..., ::-1].copy()


def mask_image(gt: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The ground-truth frame with its tool pixels (mask 0) tinted red.  uint8 RGB."""
    tool = (mask < 0.5)[..., None]
    tinted = np.where(tool, 0.4 * gt + 0.6 * np.array([1.0, 0.1, 0.1], np.float32), gt)
    return _to_u8(tinted)


def psnr(pred: np.ndarray, gt: np.ndarray) -> float:
    mse = float(np.mean((np.clip(pred, 0, 1) - gt) ** 2))
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


# ---------------------------------------------------------------------------------------------
# composition

def _label(img: np.ndarray, text: str) -> np.ndarray:
    """Write ``text`` in the top-left corner (white on a dark box), scaled to the pane."""
    img = np.ascontiguousarray(img)
    s = max(0.3, img.shape[0] / 600.0)
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, s, 1)
    cv2.rectangle(img, (0, 0), (tw + 6, th + base + 6), (0, 0, 0), -1)
    cv2.putText(img, text, (3, th + 3), cv2.FONT_HERSHEY_SIMPLEX, s, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def _fit(img: np.ndarray, w: int, h: int) -> np.ndarray:
    """Letterbox ``img`` into a w x h black box, aspect kept."""
    ih, iw = img.shape[:2]
    s = min(w / iw, h / ih)
    nw, nh = max(1, int(round(iw * s))), max(1, int(round(ih * s)))
    out = np.zeros((h, w, 3), np.uint8)
    r = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    y0, x0 = (h - nh) // 2, (w - nw) // 2
    out[y0:y0 + nh, x0:x0 + nw] = r
    return out


def pane_size(width: int, height: int, n_side: int) -> Tuple[int, int]:
    """(w, h) of each pane in a width x height image with ``n_side`` side panes: the whole image
    with none, else a 2 x 2 grid (main top left, then ground truth, error, tool mask).  The main pane
    keeps the browser's field of view, so it frames the same view at half size."""
    if n_side == 0:
        return width, height
    return max(8, (width - PANE_GAP) // 2), max(8, (height - PANE_GAP) // 2)


def compose(main: np.ndarray, side: List[Tuple[str, np.ndarray]], width: int, height: int) -> np.ndarray:
    """The streamed image: ``main`` alone, or the 2 x 2 grid of pane_size with the labelled side
    panes (letterboxed) after the main one."""
    if not side:
        return main
    pw, ph = main.shape[1], main.shape[0]
    out = np.zeros((height, width, 3), np.uint8)
    cells = [(0, 0), (0, pw + PANE_GAP), (ph + PANE_GAP, 0), (ph + PANE_GAP, pw + PANE_GAP)]
    out[:ph, :pw] = main
    for (y0, x0), (text, img) in zip(cells[1:], side):
        out[y0:y0 + ph, x0:x0 + pw] = _label(_fit(img, pw, ph), text)
    return out


def sh_basis_np(dirs: np.ndarray, degree: int) -> np.ndarray:
    """reference/project.py's sh_basis in numpy: unit directions [N, 3] -> [N, (degree+1)^2].  The
    torch one is several times slower for one call on a CPU."""
    return np.stack(sh_basis_terms(dirs[:, 0], dirs[:, 1], dirs[:, 2], degree), -1)


# ---------------------------------------------------------------------------------------------
# the model being viewed

@dataclass
class ViewState:
    """One client's settings when a frame is rendered."""
    t: float = 0.0
    mode: str = "colour"
    height: int = 256
    show_gt: bool = False
    show_error: bool = False
    show_mask: bool = False


@dataclass
class ViewResult:
    image: np.ndarray              # uint8 RGB [H, W, 3]: what is streamed
    camera: Camera                 # the main pane's camera
    t: float
    frame: Optional[int]           # the frame whose time t is, if any
    info: Dict[str, object] = field(default_factory=dict)
    render_ms: float = 0.0


class ViewerModel:
    """A loaded run on one OpenCL device: renders views for any number of clients (one at a time:
    the device queue is shared)."""

    def __init__(self, loaded, rt):
        self.run = loaded
        self.rt = rt
        self.scene = loaded.scene
        self.gaussians = loaded.gaussians
        self.params = upload(rt, loaded.gaussians)
        self.lock = threading.Lock()
        frames = self.scene.frames
        self.times = np.array([f.time for f in frames], np.float64)
        self.dt_frame = 1.0 / max(len(frames) - 1, 1)
        self.test = set(self.scene.test_indices)
        self.depth_lo_hi: Optional[Tuple[float, float]] = None
        self.flow_scale: Optional[float] = None          # fraction of the image height

    @property
    def start_camera(self) -> Camera:
        """The training camera of the first frame: where the browser starts."""
        return self.scene.frames[0].camera

    def nearest_frame(self, t: float) -> int:
        return int(np.argmin(np.abs(self.times - t)))

    def home_pose(self, k: int) -> Dict[str, object]:
        """Frame k's training camera as the browser's orbit camera: wxyz, position, fov, up (the
        camera's up, -y in OpenCV) and look_at, the orbit point: straight ahead at the median depth
        of the Gaussians in front of it (the tissue)."""
        cam = self.scene.frames[int(k)].camera
        wxyz, pos, fov = pose_of_camera(cam)
        R = quat_to_matrix(wxyz)
        m = self.gaussians.means[:, :3].astype(np.float64)
        z = (m - pos) @ R[:, 2]
        ahead = z[z > cam.near]
        focus = float(np.median(ahead)) if ahead.size else 1.0
        return {"wxyz": wxyz, "position": pos, "fov": fov, "up": -R[:, 1],
                "look_at": pos + focus * R[:, 2], "focus": focus}

    def frame_at(self, t: float, tol: float) -> Optional[int]:
        """The frame whose time is within ``tol`` of t, else None."""
        k = int(np.argmin(np.abs(self.times - t)))
        return k if abs(self.times[k] - t) <= tol else None

    def frame_kind(self, k: int) -> str:
        return "test" if k in self.test else "train"

    def render_host(self, cam: Camera, t: float, t_flow: Optional[float] = None) -> Dict[str, np.ndarray]:
        with self.lock:
            return render(self.rt, self.params, cam, float(t), t_flow, select=True).host()

    def main_view(self, cam: Camera, st: ViewState) -> Tuple[np.ndarray, Dict[str, object]]:
        """The main pane (uint8 RGB) in the chosen mode, and what its colour map means."""
        flow_t = st.t + self.dt_frame if st.mode == "flow" else None
        h = self.render_host(cam, st.t, flow_t)
        info: Dict[str, object] = {}
        if st.mode == "depth":
            if self.depth_lo_hi is None:        # fixed for the session so colours compare across time
                self.depth_lo_hi = depth_range(h["depth"], h["alpha"])
            lo, hi = self.depth_lo_hi
            info["depth_range"] = (lo, hi)
            return depth_image(h["depth"], h["alpha"], lo, hi), info
        if st.mode == "flow":
            if self.flow_scale is None:
                ok = h["alpha"] >= ALPHA_EMPTY
                mag = np.hypot(h["flow"][..., 0], h["flow"][..., 1])[ok]
                p = float(np.percentile(mag, FLOW_PERCENTILE)) if mag.size else 0.0
                self.flow_scale = max(p / cam.height, FLOW_MIN_SCALE)
            scale = self.flow_scale * cam.height
            info["flow_scale_px"] = scale
            return flow_image(h["flow"], h["alpha"], scale), info
        return _to_u8(h["image"]), info

    def view(self, pose, st: ViewState, canvas_aspect: float, tol: float) -> ViewResult:
        """Render what one client sees: pose = (wxyz, position, fov_y) of its browser camera."""
        t0 = time.perf_counter()
        W, H = render_size(st.height, canvas_aspect)
        k = self.frame_at(st.t, tol)
        wanted = [s for s, on in (("gt", st.show_gt), ("error", st.show_error),
                                  ("mask", st.show_mask and self.scene.has_masks)) if on]
        n_side = len(wanted) if k is not None else 0
        pw, ph = pane_size(W, H, n_side)
        cam = camera_from_pose(pose[0], pose[1], pose[2], pw, ph, self.start_camera.near)
        main, info = self.main_view(cam, st)
        side: List[Tuple[str, np.ndarray]] = []
        if n_side:
            f = self.scene.frames[k]
            kind = self.frame_kind(k)
            if "gt" in wanted:
                side.append((f"ground truth, frame {k} ({kind})", _to_u8(f.image)))
            if "error" in wanted:
                # the error is only meaningful from the frame's own camera: render there
                pred = self.render_host(f.camera, f.time)["image"]
                side.append((f"|render - truth| from frame {k}'s camera, full scale {ERROR_FULL_SCALE}",
                             error_image(pred, f.image, f.mask)))
                info["psnr"] = psnr(pred * (1 if f.mask is None else f.mask[..., None]),
                                    f.image * (1 if f.mask is None else f.mask[..., None]))
            if "mask" in wanted and f.mask is not None:
                side.append((f"tool mask, frame {k} (red: not supervised)", mask_image(f.image, f.mask)))
        image = compose(main, side, W, H)
        return ViewResult(image, cam, float(st.t), k, info, (time.perf_counter() - t0) * 1e3)

    # -- browser (client-side) mode --------------------------------------------------------------

    def _motion(self):
        """What of each Gaussian does not depend on t, computed once: its 4D mean, the conditional
        spatial covariance Sxx - sxt sxt^T / stt, the velocity sxt / stt and stt (export_ply.py's
        gaussians_at evaluates the same formulas, and the eigen-decomposition a PLY needs, per call)."""
        if getattr(self, "_motion_cache", None) is None:
            sigma = covariance_4d(self.gaussians)                       # [N, 4, 4] float64
            stt = sigma[:, 3, 3]
            with np.errstate(divide="ignore", invalid="ignore"):
                vel = sigma[:, :3, 3] / stt[:, None]
                cov = sigma[:, :3, :3] - sigma[:, :3, 3, None] * vel[:, None, :]
            ok = np.isfinite(stt) & (stt > 0) & np.all(np.isfinite(cov), axis=(1, 2))
            self._motion_cache = (self.gaussians.means.astype(np.float64), cov, vel, stt, ok)
        return self._motion_cache

    def splats_at(self, t: float, eye) -> Dict[str, np.ndarray]:
        """The 3D Gaussians at time t for a generic splat renderer: centres [M, 3], covariances
        [M, 3, 3] (the conditional mean and covariance given t), opacities [M, 1] (opacity x the
        temporal marginal; Gaussians below MARGINAL_CULL dropped, as the rasterizer and the PLY
        export drop them) and colours [M, 3] (TEASH colour at t, seen from ``eye``: a splat renderer
        takes one colour per Gaussian, not spherical harmonics)."""
        g = self.gaussians
        means, cov, vel, stt, ok = self._motion()
        dt = float(t) - means[:, 3]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            m = np.exp(-0.5 * dt * dt / stt)
        keep = ok & np.isfinite(m) & (m >= MARGINAL_CULL)
        dt, m = dt[keep], m[keep]
        mean = means[keep, :3] + vel[keep] * dt[:, None]
        opac = m / (1.0 + np.exp(-g.opacity[keep].astype(np.float64)))
        nt1 = g.sh.shape[1]
        cosn = np.cos(2.0 * math.pi * np.arange(nt1) / TEASH_PERIOD * float(t) + g.phase[keep].astype(np.float64))
        cosn[:, 0] = 1.0                                                # phi_0 unused (gaussians.py)
        d = mean - np.asarray(eye, np.float64)[None, :]
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        K = g.sh.shape[2]
        Y = sh_basis_np(d.astype(np.float32), int(round(math.sqrt(K))) - 1)   # [M, K]
        sh = g.sh[keep].astype(np.float32)
        rgb = 0.5 + np.einsum("nikc,nk,ni->nc", sh, Y, cosn.astype(np.float32), optimize=True)
        return {"centers": mean.astype(np.float32), "covariances": cov[keep].astype(np.float32),
                "rgbs": np.clip(rgb, 0.0, 1.0).astype(np.float32), "opacities": opac[:, None].astype(np.float32)}
