"""Synthetic endoscopic scene with known truth, written in the EndoNeRF layout.

The scene, seen by a static pinhole camera (identity pose, f = FOCAL_PER_WIDTH * width):

* Tissue: a surface seen along every pixel ray (a depth map over the image), about 3.5 to 5.5
  units deep, with a bowl shape, a tilt and folds.  It carries a vessel-like texture (branching dark
  red vessels on mottled pink).  It deforms: material point ``m`` (pixel units of the rest state) is
  seen at time t at the pixel ``p`` with ``p - w(p, t) = m``, where ``w`` is a smooth sum of
  Gaussian bumps oscillating in time (lateral motion), and its depth ``depth(m, t)`` also breathes.
  ``deformation`` scales both (0 = rigid tissue).
* Light at the camera: Blinn-Phong with the light and the eye at the origin, so the half vector is
  the view direction; inverse-square fall-off.  Wet tissue has a sharp specular lobe, so highlights
  appear on folds facing the camera and move as the tissue deforms.
* Tool: a metal capsule (shaft with a rounded tip) entering from the lower right, in front of the
  tissue, that advances, retracts and sways (a rigid motion), occluding tissue; masks/ holds 255 on
  its pixels.

Written files (all through a temporary folder renamed at the end):
  images/NNNNNN.png (RGB8), depth/NNNNNN.png (uint16, depth = value * depth_scale),
  masks/NNNNNN.png (255 = tool), poses_bounds.npy (identity poses, hwf, near/far around all depths),
  scene.json (depth_scale, parameters), gt_flow/NNNNNN.npy ([H, W, 2] float32 forward flow in pixels
  (x, y) from frame N to N+1 of whatever is visible at frame N, tissue or tool, including tissue that
  becomes hidden), gt_points/NNNNNN.npy ([H, W, 3] float32 camera-space point seen by each pixel).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np

from ..atomic import atomic_directory, save_png

FOCAL_PER_WIDTH = 0.8          # f = 0.8 W: about 64 degrees horizontal field of view
DEPTH_SCALE = 1e-3             # scene units per uint16 depth count (max 65.5 units)
TEXTURE_MARGIN = 0.15          # texture canvas extends this fraction of W beyond the image
WARP_AMPLITUDE = 0.04          # peak lateral displacement, fraction of W, at deformation 1
BREATH_AMPLITUDE = 0.25        # peak depth change (scene units) at deformation 1
N_BUMPS = 4                    # Gaussian bumps in the deformation field
FIXED_POINT_ITERS = 12         # iterations to invert the warp when computing the flow
# Blinn-Phong parameters
AMBIENT = 0.12
TISSUE_SPECULAR, TISSUE_SHININESS = 0.55, 60.0
TOOL_ALBEDO, TOOL_SPECULAR, TOOL_SHININESS = 0.22, 0.6, 30.0
LIGHT_REF_DEPTH = 4.0          # inverse-square fall-off is 1 at this distance
TOOL_RADIUS, TOOL_LENGTH = 0.22, 6.0


class _Scene:
    """The analytic scene; positions are in pixels (image) or scene units (camera space)."""

    def __init__(self, width, height, frames, seed, deformation):
        self.W, self.H, self.N = width, height, frames
        self.deformation = float(deformation)
        self.f = FOCAL_PER_WIDTH * width
        self.cx, self.cy = width / 2.0, height / 2.0
        rng = np.random.default_rng(seed)
        self.rng = rng
        u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)   # [H, W] pixel centres
        self.u, self.v = u, v
        # unit-depth rays [H, W, 3]
        self.rays = np.stack([(u - self.cx) / self.f, (v - self.cy) / self.f, np.ones_like(u)], -1)
        # deformation field: bumps with centres, widths, directions, temporal frequency and phase
        self.bump_c = rng.uniform([0, 0], [width, height], size=(N_BUMPS, 2))
        self.bump_s = rng.uniform(0.2, 0.35, size=N_BUMPS) * width
        ang = rng.uniform(0, 2 * np.pi, size=N_BUMPS)
        self.bump_dir = np.stack([np.cos(ang), np.sin(ang)], -1)
        self.bump_freq = rng.uniform(0.6, 1.2, size=N_BUMPS)   # cycles per sequence
        self.bump_phase = rng.uniform(0, 2 * np.pi, size=N_BUMPS)
        self.fold_k = rng.uniform(2.5, 4.0, size=(3, 2)) * rng.choice([-1, 1], size=(3, 2))
        self.fold_phase = rng.uniform(0, 2 * np.pi, size=3)
        self.tool_phase = rng.uniform(0, 2 * np.pi)
        self.texture = _vessel_texture(rng, width, height)   # [Ht, Wt, 3]
        self.margin = TEXTURE_MARGIN * width

    # --- tissue -------------------------------------------------------------------------
    def _bump_weights(self, x, y):   # -> [..., N_BUMPS]
        dx = x[..., None] - self.bump_c[:, 0]
        dy = y[..., None] - self.bump_c[:, 1]
        return np.exp((dx * dx + dy * dy) * (-0.5 / self.bump_s ** 2))

    def _bump_time(self, t):         # [N_BUMPS]
        return np.sin(2 * np.pi * self.bump_freq * t + self.bump_phase)

    def warp(self, x, y, t):
        """Lateral displacement w(p, t) in pixels at image positions (x, y): two arrays like x."""
        gain = self.deformation * WARP_AMPLITUDE * self.W * self._bump_time(t)       # [N_BUMPS]
        w = self._bump_weights(x, y) @ (gain[:, None] * self.bump_dir)             # [..., 2]
        return w[..., 0], w[..., 1]

    def material(self, x, y, t):
        wx, wy = self.warp(x, y, t)
        return x - wx, y - wy

    def tissue_depth(self, mx, my, t):
        """Depth along the ray (z, scene units) of material point (mx, my) at time t."""
        xn = (mx - self.cx) / self.W            # about [-0.5, 0.5]
        yn = (my - self.cy) / self.W            # about [-0.4, 0.4]
        z = 4.4 + 1.5 * yn + 1.6 * (xn ** 2 + yn ** 2)
        for k in range(3):
            z = z + 0.06 * np.sin(2 * np.pi * (self.fold_k[k, 0] * xn + self.fold_k[k, 1] * yn)
                                  + self.fold_phase[k])
        breath = self._bump_weights(mx, my) @ np.cos(2 * np.pi * self.bump_freq * t + self.bump_phase)
        return z + self.deformation * BREATH_AMPLITUDE * breath

    def tissue(self, t):
        """Tissue at time t: albedo [H, W, 3], points [H, W, 3] (camera space)."""
        mx, my = self.material(self.u, self.v, t)
        z = self.tissue_depth(mx, my, t)
        points = self.rays * z[..., None]
        map_x = (mx + self.margin - 0.5).astype(np.float32)   # texture pixel centres at integer + 0.5
        map_y = (my + self.margin - 0.5).astype(np.float32)
        albedo = cv2.remap(self.texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        return albedo, points

    def tissue_flow(self, t0, t1):
        """[H, W, 2] pixel motion of the tissue point seen at each pixel at t0, to its place at t1."""
        mx, my = self.material(self.u, self.v, t0)
        px, py = self.u.copy(), self.v.copy()
        for _ in range(FIXED_POINT_ITERS):     # p' = m + w(p', t1): a contraction, |grad w| << 1
            wx, wy = self.warp(px, py, t1)
            px, py = mx + wx, my + wy
        rx, ry = self.material(px, py, t1)
        if not max(np.abs(rx - mx).max(), np.abs(ry - my).max()) < 1e-4:
            raise ValueError(f"--deformation {self.deformation:g} folds the tissue over itself at this size and "
                             f"seed (its warp has no inverse); use a smaller one (the default is 1)")
        return np.stack([px - self.u, py - self.v], -1)

    # --- tool ---------------------------------------------------------------------------
    def tool_pose(self, t):
        """Rotation [3, 3] (local z = shaft axis, tip -> handle) and tip position [3] at time t."""
        s = 2 * np.pi * t
        insert = 0.5 * math.sin(1.3 * s + self.tool_phase)           # along the shaft
        sway = 0.12 * math.sin(0.9 * s + 0.7 * self.tool_phase)      # rotation about the view axis
        axis = np.array([0.55 + sway, 0.45 - sway, -0.55])
        axis /= np.linalg.norm(axis)
        tip = np.array([0.05 * self.W / self.f * 4.0, 0.0, 3.3]) - insert * axis
        z = axis
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        return np.stack([x, y, z], 1), tip

    def tool(self, t):
        """Tool at time t: hit distance along the unit-depth ray (inf = miss) [H, W], normals [H, W, 3]."""
        R, tip = self.tool_pose(t)
        end = tip + R[:, 2] * TOOL_LENGTH
        z, n = _capsule_hit(self.rays, tip, end, TOOL_RADIUS)
        return z, n

    def tool_flow(self, points, t0, t1):
        R0, tip0 = self.tool_pose(t0)
        R1, tip1 = self.tool_pose(t1)
        local = (points - tip0) @ R0             # [H, W, 3] tool coordinates
        moved = local @ R1.T + tip1
        return self.project(moved) - np.stack([self.u, self.v], -1)

    def project(self, pts):  # [..., 3] -> [..., 2] pixel positions
        return np.stack([self.f * pts[..., 0] / pts[..., 2] + self.cx,
                         self.f * pts[..., 1] / pts[..., 2] + self.cy], -1)

    # --- one frame ----------------------------------------------------------------------
    def frame(self, i):
        """rgb [H, W, 3] float in [0, 1], depth [H, W], tool [H, W] bool, points [H, W, 3], flow to i+1."""
        t = i / max(self.N - 1, 1)
        albedo, tpoints = self.tissue(t)
        tissue_rgb = _shade(tpoints, _normals(tpoints), albedo, TISSUE_SPECULAR, TISSUE_SHININESS)
        tz, tn = self.tool(t)
        tool = tz < tpoints[..., 2]
        tool_points = self.rays * np.where(tool, tz, 1.0)[..., None]
        tool_rgb = _shade(tool_points, tn, np.full(tn.shape, TOOL_ALBEDO), TOOL_SPECULAR, TOOL_SHININESS)
        rgb = np.where(tool[..., None], tool_rgb, tissue_rgb)
        points = np.where(tool[..., None], tool_points, tpoints)
        flow = None
        if i + 1 < self.N:
            t1 = (i + 1) / (self.N - 1)
            flow = np.where(tool[..., None], self.tool_flow(points, t, t1), self.tissue_flow(t, t1))
        return np.clip(rgb, 0, 1), points[..., 2], tool, points, flow


def _capsule_hit(rays, a, b, r):
    """Ray (origin 0, direction ``rays`` [H, W, 3] with z = 1) against the capsule a-b of radius r.

    Returns the depth z of the first hit [H, W] (inf where it misses) and the unit normal [H, W, 3].
    """
    norm = np.linalg.norm(rays, axis=-1, keepdims=True)
    rd = rays / norm                                          # unit directions
    ba = b - a
    oa = -a
    baba = ba @ ba
    bard = rd @ ba
    baoa = oa @ ba
    rdoa = rd @ oa
    oaoa = oa @ oa
    qa = baba - bard ** 2
    qb = baba * rdoa - baoa * bard
    qc = baba * oaoa - baoa ** 2 - r * r * baba
    h = qb ** 2 - qa * qc
    with np.errstate(invalid="ignore", divide="ignore"):
        t_body = (-qb - np.sqrt(h)) / qa
        y = baoa + t_body * bard
        t = np.where((h >= 0) & (y > 0) & (y < baba) & (t_body > 0), t_body, np.inf)
        for c in (a, b):                                      # spherical caps
            oc = -c
            cb = rd @ oc
            cc = oc @ oc - r * r
            ch = cb ** 2 - cc
            tc = -cb - np.sqrt(ch)
            t = np.where((ch >= 0) & (tc > 0) & (tc < t), tc, t)
    hit = np.isfinite(t)
    p = rd * np.where(hit, t, 0.0)[..., None]
    s = np.clip(((p - a) @ ba) / baba, 0.0, 1.0)
    n = (p - (a + s[..., None] * ba)) / r
    z = np.where(hit, t / norm[..., 0], np.inf)               # distance along the unit-depth ray = z
    return z, n


def _normals(points):
    """Unit normals [H, W, 3] of a point map [H, W, 3], facing the camera."""
    du = np.gradient(points, axis=1)
    dv = np.gradient(points, axis=0)
    n = np.cross(du, dv)
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-12
    flip = (n * points).sum(-1) > 0                            # must point back towards the origin
    return np.where(flip[..., None], -n, n)


def _shade(points, normals, albedo, ks, shininess):
    """Blinn-Phong, light and eye at the origin (half vector = view vector), inverse-square fall-off."""
    dist = np.linalg.norm(points, axis=-1, keepdims=True)
    l = -points / np.maximum(dist, 1e-9)
    ndl = np.clip((normals * l).sum(-1, keepdims=True), 0.0, 1.0)
    fall = (LIGHT_REF_DEPTH / np.maximum(dist, 1e-9)) ** 2
    return fall * (albedo * (AMBIENT + (1 - AMBIENT) * ndl) + ks * ndl ** shininess)


def _smooth_noise(rng, h, w, sigma):
    n = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), sigma)
    return n / (n.std() + 1e-9)


def _vessel_texture(rng, width, height):
    """[Ht, Wt, 3] float32 RGB albedo: mottled pink tissue with branching dark-red vessels."""
    margin = int(math.ceil(TEXTURE_MARGIN * width))
    wt, ht = width + 2 * margin, height + 2 * margin
    ss = 4                                                    # supersampling for the vessel drawing
    vessels = np.zeros((ht * ss, wt * ss), np.uint8)
    stack = []
    for _ in range(max(6, (wt * ht) // 1500)):
        stack.append((rng.uniform(0, wt), rng.uniform(0, ht), rng.uniform(0, 2 * np.pi), 2.2, 0))
    while stack:
        x, y, ang, thick, depth = stack.pop()
        length = rng.uniform(0.3, 0.8) * width / (1 + depth)
        pts = [(x, y)]
        for _ in range(int(length / 2)):
            ang += rng.normal(0, 0.25)
            x, y = x + 2 * math.cos(ang), y + 2 * math.sin(ang)
            pts.append((x, y))
            if depth < 3 and rng.random() < 0.03:
                stack.append((x, y, ang + rng.choice([-1, 1]) * rng.uniform(0.5, 1.1),
                              max(0.8, thick * 0.65), depth + 1))
        arr = (np.array(pts) * ss).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(vessels, [arr], False, 255, thickness=max(1, int(round(thick * ss))),
                      lineType=cv2.LINE_AA)
    v = cv2.resize(vessels.astype(np.float32) / 255.0, (wt, ht), interpolation=cv2.INTER_AREA)
    v = cv2.GaussianBlur(v, (0, 0), 0.6)[..., None]
    base = np.array([0.86, 0.46, 0.40], np.float32)
    vessel = np.array([0.50, 0.10, 0.12], np.float32)
    low = _smooth_noise(rng, ht, wt, 0.12 * width)[..., None]
    fine = _smooth_noise(rng, ht, wt, 1.0)[..., None]
    tissue = base * (1 + 0.10 * low) + 0.035 * fine
    return np.clip(tissue * (1 - v) + vessel * v, 0, 1).astype(np.float32)


# limits of the generator's parameters: a larger deformation folds the tissue (no inverse warp; inf
# hung in cv2.remap), larger frames exhaust memory
MAX_DEFORMATION = 10.0
MAX_SIDE = 8192
MAX_PIXELS = 2e9


def make_synthetic_scene(out, width: int = 160, height: int = 128, frames: int = 24, seed: int = 0,
                         deformation: float = 1.0, force: bool = False) -> Path:
    """Generate a synthetic scene in ``out`` (see the module docstring) and return its path.

    ``out`` must be absent or empty unless ``force``; nothing is half-written (temporary folder
    + rename).  Raises DataError for a non-empty ``out`` and ValueError for bad parameters.
    """
    if width < 16 or height < 16:
        raise ValueError(f"--width / --height {width}x{height} is too small (at least 16x16)")
    if max(width, height) > MAX_SIDE or width * height * frames > MAX_PIXELS:
        raise ValueError(f"{width}x{height} x {frames} frames is too large (at most {MAX_SIDE} pixels a side and "
                         f"{MAX_PIXELS:.0e} pixels in all)")
    if frames < 2:
        raise ValueError(f"--frames: need at least 2 frames, got {frames}")
    if not (math.isfinite(deformation) and 0 <= deformation <= MAX_DEFORMATION):
        raise ValueError(f"--deformation must be a number from 0 to {MAX_DEFORMATION:g}, got {deformation}")
    if not 0 <= seed < 2 ** 63:
        raise ValueError(f"--seed must be a whole number from 0 to 2**63 - 1, got {seed}")
    out = Path(out)
    sc = _Scene(width, height, frames, seed, deformation)
    with atomic_directory(out, force=force) as tmp:
        for sub in ("images", "depth", "masks", "gt_flow", "gt_points"):
            (tmp / sub).mkdir()
        zmin, zmax = np.inf, 0.0
        for i in range(frames):
            rgb, depth, tool, points, flow = sc.frame(i)
            name = f"{i:06d}"
            save_png(tmp / "images" / f"{name}.png", (rgb[..., ::-1] * 255 + 0.5).astype(np.uint8), atomic=False)
            save_png(tmp / "depth" / f"{name}.png",
                     np.clip(np.round(depth / DEPTH_SCALE), 1, 65535).astype(np.uint16), atomic=False)
            save_png(tmp / "masks" / f"{name}.png", np.where(tool, 255, 0).astype(np.uint8), atomic=False)
            np.save(tmp / "gt_points" / f"{name}.npy", points.astype(np.float32))
            if flow is not None:
                np.save(tmp / "gt_flow" / f"{name}.npy", flow.astype(np.float32))
            zmin, zmax = min(zmin, float(depth.min())), max(zmax, float(depth.max()))
        near, far = 0.9 * zmin, 1.1 * zmax
        pose = np.concatenate([np.eye(3), np.zeros((3, 1)), [[height], [width], [sc.f]]], 1)  # [3, 5]
        row = np.concatenate([pose.reshape(-1), [near, far]])
        np.save(tmp / "poses_bounds.npy", np.tile(row, (frames, 1)))
        info = {
            "generator": "endowave-cl synth",
            "depth_scale": DEPTH_SCALE,
            "hwf_layout": "hwf",
            "params": {"width": width, "height": height, "frames": frames, "seed": seed,
                       "deformation": deformation},
            "units": "depth and gt_points in scene units; depth = png value * depth_scale",
            "gt_flow": "gt_flow/NNNNNN.npy: [H, W, 2] float32 forward flow (x, y) in pixels from frame "
                       "NNNNNN to the next, of the surface visible at NNNNNN",
            "gt_points": "gt_points/NNNNNN.npy: [H, W, 3] float32 camera-space point seen by each pixel",
        }
        (tmp / "scene.json").write_text(json.dumps(info, indent=2) + "\n")
    return out
