"""Torch references of the tile rasterizer (docs/ARCHITECTURE.md "rasterize").

Compositing rules, for pixel centre p = (i + 0.5, j + 0.5) and Gaussian k, d = mean2d - p:
    power = -0.5 (a dx^2 + c dy^2) - b dx dy           skip when power > 0
    alpha = min(ALPHA_MAX, opac exp(power))            skip when alpha < ALPHA_MIN
    T_next = T (1 - alpha)                             stop *before* k when T_next < T_STOP
    out += features[k] alpha T;  T = T_next
Outputs out [H,W,C], alpha [H,W] = 1 - T_final, T_final [H,W], last [H,W] int32 (one past the
last contributor, relative to the tile's range start; 0 when nothing contributed).

``rasterize_ref`` walks the sorted (tile, depth) list; ``rasterize_dense_ref`` does not use it: for
each tile it selects every Gaussian whose tile rect holds the tile and orders them by (depth, index).
Both are differentiable with torch autograd w.r.t. means2d, conic, opac, features (that gives the
reference adjoint ``rasterize_bwd_ref``). ``accumulate_densify_stats_ref`` is the numpy reference of
the densification statistics.
"""
from __future__ import annotations

from typing import Tuple

import numpy as np
import torch

from ..layout import ALPHA_MAX, ALPHA_MIN, T_STOP, TILE, tile_grid  # noqa: F401  (constants: endowave_cl/layout.py)


def _as_t(x, dtype=torch.float32):
    if isinstance(x, torch.Tensor):
        return x
    return torch.as_tensor(np.asarray(x), dtype=dtype)


def _composite_tile(means2d, conic, opac, features, idx, px, py):
    """Composite the Gaussians idx [K] (front to back) over the pixels (px, py) [P].

    Returns out [P, C], T_final [P], last [P] (int64, one past the last contributor in idx order).
    """
    P = px.shape[0]
    C = features.shape[1]
    if idx.numel() == 0:
        return (torch.zeros(P, C, dtype=features.dtype) + 0 * features.sum(),
                torch.ones(P, dtype=features.dtype), torch.zeros(P, dtype=torch.int64))
    m = means2d[idx]                                   # [K, 2]
    cn = conic[idx]                                    # [K, 3]
    dx = m[None, :, 0] - px[:, None]                   # [P, K]
    dy = m[None, :, 1] - py[:, None]                   # [P, K]
    power = -0.5 * (cn[None, :, 0] * dx * dx + cn[None, :, 2] * dy * dy) - cn[None, :, 1] * dx * dy
    alpha = torch.clamp(opac[idx][None, :] * torch.exp(power), max=ALPHA_MAX)   # [P, K]
    with torch.no_grad():
        valid = (power <= 0) & (alpha >= ALPHA_MIN)                             # [P, K]
        a_valid = torch.where(valid, alpha, torch.zeros_like(alpha))
        t_incl = torch.cumprod(1.0 - a_valid, dim=1)                            # [P, K]
        contrib = valid & (t_incl >= T_STOP)                                   # [P, K]
        k_ids = torch.arange(1, idx.numel() + 1, dtype=torch.int64)
        last = (contrib.to(torch.int64) * k_ids[None, :]).max(dim=1).values    # [P]
    a_c = torch.where(contrib, alpha, torch.zeros_like(alpha))                 # [P, K]
    one_minus = 1.0 - a_c
    t_incl = torch.cumprod(one_minus, dim=1)                                  # [P, K]
    t_excl = torch.cat([torch.ones(P, 1, dtype=alpha.dtype), t_incl[:, :-1]], dim=1)
    w = a_c * t_excl                                                          # [P, K]
    out = w @ features[idx]                                                   # [P, C]
    return out, t_incl[:, -1], last


def _pixel_grid(tx, ty, width, height):
    """Pixel centres of tile (tx, ty) that lie inside the image: px, py [P] float, ix, iy [P] int."""
    xs = torch.arange(tx * TILE, min((tx + 1) * TILE, width))
    ys = torch.arange(ty * TILE, min((ty + 1) * TILE, height))
    iy, ix = torch.meshgrid(ys, xs, indexing="ij")
    ix, iy = ix.reshape(-1), iy.reshape(-1)
    return ix.float() + 0.5, iy.float() + 0.5, ix, iy


def _assemble(tiles, width, height, C, dtype):
    """Stitch per-tile results into images (out [H,W,C], alpha, T_final, last), one scatter each."""
    flat = torch.cat([iy * width + ix for (ix, iy, _, _, _) in tiles])          # [H*W]
    out = torch.zeros(height * width, C, dtype=dtype).index_put((flat,), torch.cat([t[2] for t in tiles]))
    T = torch.ones(height * width, dtype=dtype).index_put((flat,), torch.cat([t[3] for t in tiles]))
    last = torch.zeros(height * width, dtype=torch.int32)
    last[flat] = torch.cat([t[4] for t in tiles]).to(torch.int32)
    T = T.reshape(height, width)
    return out.reshape(height, width, C), 1.0 - T, T, last.reshape(height, width)


def rasterize_ref(means2d, conic, opac, features, sorted_values, tile_ranges, width: int, height: int
                  ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Reference of the ``rasterize`` kernel, walking the sorted list tile by tile.

    means2d [N,2], conic [N,3], opac [N], features [N,C] (torch tensors, may require grad),
    sorted_values [M] int, tile_ranges [n_tiles, 2] int.
    Returns out [H,W,C], alpha [H,W], T_final [H,W], last [H,W] int32.
    """
    means2d, conic, opac, features = (_as_t(x) for x in (means2d, conic, opac, features))
    values = torch.as_tensor(np.asarray(sorted_values, np.int64).reshape(-1))
    ranges = np.asarray(tile_ranges, np.int64).reshape(-1, 2)
    tiles_x, tiles_y = tile_grid(width, height)
    tiles = []
    for ty in range(tiles_y):
        for tx in range(tiles_x):
            s, e = ranges[ty * tiles_x + tx]
            px, py, ix, iy = _pixel_grid(tx, ty, width, height)
            o, t, l = _composite_tile(means2d, conic, opac, features, values[s:e], px, py)
            tiles.append((ix, iy, o, t, l))
    return _assemble(tiles, width, height, features.shape[1], features.dtype)


def rasterize_dense_ref(means2d, conic, opac, features, depth, rect, width: int, height: int
                        ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Reference of the whole tile forward pass without the sorted list.

    For each tile: every Gaussian whose rect [N,4] (x0, y0, x1, y1, exclusive, in tiles) holds the
    tile, ordered by (depth, index) (a Gaussian with an empty rect, e.g. radius 0, is never used).
    Same outputs as ``rasterize_ref``; ``last`` counts in that per-tile order.
    """
    means2d, conic, opac, features = (_as_t(x) for x in (means2d, conic, opac, features))
    depth = np.asarray(depth, np.float32).reshape(-1)
    rect = np.asarray(rect, np.int64).reshape(-1, 4)
    tiles_x, tiles_y = tile_grid(width, height)
    order = np.lexsort((np.arange(len(depth)), depth))      # by depth, then index
    r_sorted = rect[order]
    tiles = []
    for ty in range(tiles_y):
        row = order[(r_sorted[:, 1] <= ty) & (ty < r_sorted[:, 3])]
        r_row = rect[row]
        for tx in range(tiles_x):
            sel = row[(r_row[:, 0] <= tx) & (tx < r_row[:, 2])]
            px, py, ix, iy = _pixel_grid(tx, ty, width, height)
            o, t, l = _composite_tile(means2d, conic, opac, features, torch.as_tensor(sel, dtype=torch.int64),
                                      px, py)
            tiles.append((ix, iy, o, t, l))
    return _assemble(tiles, width, height, features.shape[1], features.dtype)


def rasterize_bwd_ref(means2d, conic, opac, features, sorted_values, tile_ranges, width, height,
                      v_out, v_alpha):
    """Reference adjoint of ``rasterize`` by torch autograd: dict of numpy arrays
    v_means2d [N,2], v_conic [N,3], v_opac [N], v_features [N,C]."""
    leaves = [torch.tensor(np.asarray(x, np.float32), requires_grad=True)
              for x in (means2d, conic, opac, features)]
    out, alpha, _, _ = rasterize_ref(*leaves, sorted_values, tile_ranges, width, height)
    loss = (out * _as_t(v_out)).sum() + (alpha * _as_t(v_alpha)).sum()
    grads = torch.autograd.grad(loss, leaves, allow_unused=True)
    names = ("v_means2d", "v_conic", "v_opac", "v_features")
    return {n: (g.numpy() if g is not None else np.zeros_like(leaf.detach().numpy()))
            for n, g, leaf in zip(names, grads, leaves)}


def accumulate_densify_stats_ref(v_means2d, radius, width, height, grad_accum, count, max_radius):
    """numpy reference of ``accumulate_densify_stats``; returns new (grad_accum, count, max_radius).

    For visible Gaussians (radius > 0): grad_accum += |v_means2d * (W/2, H/2)| (Euclidean norm of the
    gradient in NDC units), count += 1, max_radius = max(max_radius, radius).
    """
    v = np.asarray(v_means2d, np.float32).reshape(-1, 2)
    radius = np.asarray(radius).reshape(-1)
    vis = radius > 0
    g = np.asarray(grad_accum, np.float32).copy()
    n = np.asarray(count, np.int32).copy()
    mr = np.asarray(max_radius, np.float32).copy()
    scaled = v * np.array([0.5 * width, 0.5 * height], np.float32)
    norm = np.sqrt((scaled * scaled).sum(1)).astype(np.float32)
    g[vis] += norm[vis]
    n[vis] += 1
    mr[vis] = np.maximum(mr[vis], radius[vis].astype(np.float32))
    return g, n, mr
