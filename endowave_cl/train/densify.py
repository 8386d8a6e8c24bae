"""Adaptive density control in 4D (3DGS's clone / split / prune, 4DGS's 4D split), on the host.

``densify_and_prune`` works on a host copy (``Gaussians``) of the parameters, every few hundred
steps; the trainer uploads the result and rebuilds the Adam moments with ``source_index``.

Rules (3DGS defaults from TrainConfig):
- A Gaussian is a candidate when its mean screen-space gradient grad_accum / count (NDC units,
  accumulated by rasterize_bwd) is >= densify_grad_threshold (resolved per frame size:
  config.py DENSIFY_GRAD_THRESHOLD).
- A Gaussian's spatial size is the largest std of its conditional 3D Gaussian (the same at every
  time; train/motion.py ``spatial_size``), not of its 4D principal axes: a moving Gaussian's
  longest axis runs along its path through space-time.
- Candidates whose spatial size is <= percent_dense x extent are CLONED (an identical
  copy is appended; the original stays).
- Larger candidates are SPLIT into split_children children placed evenly along the major axis of
  the parent's conditional spatial covariance, with that axis's std divided by
  split_scale_divisor and the spacing chosen so that the children together keep the parent's
  variance (``split_along_major_axis``).  Velocity, lifetime and time centre are the parent's: the
  split is triggered by a screen-space (spatial) gradient, which says nothing about time, and
  children that kept the lifetime but were drawn at other times (4DGS samples the 4D Gaussian)
  would stack where the parent was alone.  Every other parameter is copied; the parent is removed.
  (Drawing centres at random, as 3DGS does, leaves holes where both children land on one side,
  and costs more PSNR at each densification than this rule: docs/ARCHITECTURE.md, Figures.)
- Clones, the Gaussians they were cloned from, and split children get the opacity that, stacked
  k-fold, composites to the original's (``share_opacity``; Rota Bulo et al. 2024), so density
  control does not brighten what was already fitted.
- When the scene already holds max_gaussians, nothing is added; when the candidates would exceed
  it, those with the largest gradient are taken first.  With cap_turnover > 0, up to
  cap_turnover x max_gaussians of the least opaque Gaussians that are not candidates are removed to
  make room for the candidates that did not fit (as many as those need, and no more): at the cap,
  density control keeps moving Gaussians from where they add little to where the gradient is.
- Then PRUNE: sigmoid(opacity) < prune_opacity, or a covariance that overflows float64 (log scales
  run away); and, when ``prune_big`` (off by default; 3DGS
  turns it on once step > opacity_reset_every, pass prune_big=step > cfg.opacity_reset_every),
  Gaussians whose max screen radius (pixels) exceeded prune_screen_size
  or whose spatial size exceeds prune_world_size x extent.  Screen radii are only known
  for rows that existed before this call: new rows (clones, children) are not screen-pruned.
  (3DGS resets its radii before this test, which disables it; we apply it as intended.)

Output order: surviving original rows (ascending old index), then clones, then split children.
``source_index[i]`` is the old row that new row i came from (clones and children: their parent);
``stats["is_new"]`` marks the rows the trainer must give zero Adam moments, and
``moment_source_index`` turns the pair into what ``DeviceAdam.remap`` takes.

``temporal_row_order`` is the order the trainer then stores the rows in (a permutation: every
Gaussian computes what it did): the Gaussians alive at any one time lie in few runs of rows, so
that the steps' row gathers and Adam on the selected rows (ops/select.py) read whole cache lines.
"""
from __future__ import annotations

import math
from typing import Dict, Optional, Tuple

import numpy as np

from ..gaussians import MARGINAL_CULL, PARAM_NAMES, Gaussians, covariance_4d
from .motion import gaussian_from_covariance, motion_of, moving_covariance, spatial_size


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))


def logit(p: float) -> float:
    return float(math.log(p / (1.0 - p)))


def share_opacity(logit_opacity: np.ndarray, k: int) -> np.ndarray:
    """Logit of the opacity o' with 1 - (1 - o')^k = o: k copies stacked on one another composite to
    the parent's opacity (Rota Bulo et al. 2024, "Revising densification in Gaussian splatting"),
    so that density control does not brighten or darken what was already fitted."""
    o = sigmoid(logit_opacity)
    o = 1.0 - (1.0 - o) ** (1.0 / max(int(k), 1))
    o = np.clip(o, 1e-7, 1.0 - 1e-7)
    return np.log(o / (1.0 - o)).astype(np.float32)


def split_along_major_axis(g: Gaussians, k: int, divisor: float = 1.6):
    """Children of rows that come in runs of k copies of their parent (rows r*k .. r*k + k - 1):
    (means, log scales, q_l, q_r).  In units of the parent's std along the major axis of its
    conditional spatial covariance, the children's std there is 1 / divisor and their centres are
    evenly spaced over [-a, a] with mean square offset 1 - 1 / divisor^2, so the mixture keeps the
    parent's variance (2 children, divisor 1.6: offsets +-0.78, std 0.625).  Velocity, lifetime and
    the time centre are the parent's, so every child moves along its parent's path."""
    cond, sigma_t, vel = motion_of(covariance_4d(g))                       # [n, 3, 3], [n], [n, 3]
    lam, U = np.linalg.eigh(cond)                                          # ascending
    axis = U[:, :, 2]                                                      # [n, 3]
    sd = np.sqrt(np.maximum(lam[:, 2], 0.0))                               # [n]
    child_sd = min(1.0, 1.0 / float(divisor)) if k > 1 else 1.0
    a = math.sqrt((1.0 - child_sd ** 2) * 3.0 * (k - 1) / (k + 1)) if k > 1 else 0.0
    c = np.tile(np.linspace(-a, a, k), len(g) // max(k, 1))                # [n]
    means = g.means.astype(np.float64)
    means[:, :3] += (c * sd)[:, None] * axis
    cond = cond - ((1.0 - child_sd ** 2) * lam[:, 2])[:, None, None] * axis[:, :, None] * axis[:, None, :]
    log_s, q_l, q_r = gaussian_from_covariance(moving_covariance(cond, sigma_t, vel))
    return means.astype(np.float32), log_s.astype(np.float32), q_l.astype(np.float32), q_r.astype(np.float32)


LIFETIME_CLASSES = 8   # temporal_row_order: live-interval lengths in eighths of [0, 1]


def temporal_row_order(g: Gaussians) -> np.ndarray:
    """int64 [N]: g's rows ordered by the length of their live interval within the sequence's times
    [0, 1] (rounded to 1 / LIFETIME_CLASSES, longest first), then by its centre; ties keep their
    order (a stable sort, so a clone stays behind the row it was cloned from).  A Gaussian is alive
    at t where its marginal temporal weight exp(-(t - mu_t)^2 / (2 Sigma_tt)) is at least
    MARGINAL_CULL (ops/select.py), an interval of half-width sqrt(-2 ln(MARGINAL_CULL) Sigma_tt)
    around mu_t: in this order the rows alive at one time are a band of centres in each class."""
    n = len(g)
    if n == 0:
        return np.zeros(0, np.int64)
    with np.errstate(all="ignore"):
        stt = covariance_4d(g)[:, 3, 3]                                            # [N]
        half = np.sqrt(np.maximum(stt, 0.0) * (-2.0 * math.log(MARGINAL_CULL)))
        mu = g.means[:, 3].astype(np.float64)
        lo, hi = np.clip(mu - half, 0.0, 1.0), np.clip(mu + half, 0.0, 1.0)
        length = np.where(np.isfinite(hi - lo), hi - lo, 0.0)                      # NaN: class 0
        centre = np.where(np.isfinite(lo + hi), 0.5 * (lo + hi), 0.0)
    return np.lexsort((centre, -np.round(length * LIFETIME_CLASSES))).astype(np.int64)


def _take(g: Gaussians, rows: np.ndarray) -> Dict[str, np.ndarray]:
    return {n: getattr(g, n)[rows] for n in PARAM_NAMES}


def densify_and_prune(g: Gaussians, grad_accum: np.ndarray, count: np.ndarray, max_radius: np.ndarray,
                      cfg, extent: float, prune_big: bool = False,
                      stats: Optional[dict] = None) -> Tuple[Gaussians, np.ndarray]:
    """Clone, split (4D) and prune; see the module docstring.  Returns (new_g, source_index [M]).

    grad_accum [N], count [N] (number of views that saw each Gaussian), max_radius [N] (pixels);
    extent: scene extent (world units); stats (optional dict) receives cloned / split / pruned
    counts and is_new [M] bool.
    """
    if not cfg.densify_grad_threshold > 0:
        raise ValueError("densify_grad_threshold is not resolved (TrainConfig.resolve_density)")
    N = len(g)
    grad_accum = np.asarray(grad_accum, np.float64).reshape(N)
    count = np.asarray(count, np.float64).reshape(N)
    max_radius = np.asarray(max_radius, np.float64).reshape(N)
    mean_grad = np.where(count > 0, grad_accum / np.maximum(count, 1.0), 0.0)  # [N]
    with np.errstate(all="ignore"):
        cov = covariance_4d(g) if N else np.zeros((0, 4, 4))                   # [N, 4, 4]
    sane = np.isfinite(cov).all(axis=(1, 2))      # log scales that overflow: removed below
    max_scale = np.full(N, np.inf)
    max_scale[sane] = spatial_size(cov[sane])                                  # [N]

    candidate = (mean_grad >= cfg.densify_grad_threshold) & sane
    # max_gaussians 0 (not resolved per pixel, as the trainer does): no cap
    budget = max(0, int(cfg.max_gaussians) - N) if cfg.max_gaussians > 0 else 2 ** 62
    children = int(cfg.split_children)
    small = max_scale <= cfg.percent_dense * extent
    cost = np.where(small, 1, children - 1)  # rows added: a clone adds 1, a split children - 1
    chosen = np.zeros(N, bool)
    victim = np.zeros(N, bool)    # [N] removed to make room for candidates (cap_turnover)
    if candidate.any():
        order = np.flatnonzero(candidate)
        order = order[np.argsort(-mean_grad[order], kind="stable")]  # largest gradient first
        spent = np.cumsum(cost[order])                               # [C]
        # At the cap, up to cap_turnover x cap of the least opaque non-candidates give their rows to
        # the candidates that did not fit, largest gradient first.
        turnover = int(cfg.cap_turnover * cfg.max_gaussians) if cfg.max_gaussians > 0 else 0
        if turnover > 0 and spent[-1] > budget:
            pool = np.flatnonzero(~candidate)
            pool = pool[np.argsort(sigmoid(g.opacity[pool]), kind="stable")][:turnover]   # [V]
            taken = spent[spent <= budget + pool.size]        # what the candidates that now fit take
            needed = int(max(0, taken[-1] - budget)) if taken.size else 0
            victim[pool[:needed]] = True
            budget += needed
        fits = spent <= budget
        chosen[order[fits]] = True
    clone = chosen & small        # [N]
    split = chosen & ~small       # [N]

    # -- clones: exact copies of their parent ----------------------------------------------------
    clone_rows = np.flatnonzero(clone)
    # -- split children: centres sampled from the parent's 4D Gaussian ---------------------------
    split_rows = np.flatnonzero(split)
    parents = np.repeat(split_rows, children)                                  # [S * children]
    child = _take(g, parents)
    if parents.size:
        child["means"], child["scales"], child["quat_l"], child["quat_r"] = split_along_major_axis(
            Gaussians(**child), children, cfg.split_scale_divisor)
        child["opacity"] = share_opacity(child["opacity"], children)

    keep_rows = np.flatnonzero(~split)
    parts = [_take(g, keep_rows), _take(g, clone_rows), child]
    clones_kept = np.isin(keep_rows, clone_rows)
    parts[0]["opacity"] = parts[0]["opacity"].copy()
    parts[0]["opacity"][clones_kept] = share_opacity(parts[0]["opacity"][clones_kept], 2)
    parts[1]["opacity"] = share_opacity(parts[1]["opacity"], 2)
    new = {n: np.concatenate([p[n] for p in parts], 0) for n in PARAM_NAMES}
    source = np.concatenate([keep_rows, clone_rows, parents]).astype(np.int64)   # [M]
    is_new = np.concatenate([np.zeros(keep_rows.size, bool), np.ones(clone_rows.size + parents.size, bool)])
    radius_known = np.concatenate([max_radius[keep_rows], np.zeros(clone_rows.size + parents.size)])

    # -- prune ------------------------------------------------------------------------------------
    prune = (sigmoid(new["opacity"]) < cfg.prune_opacity) | ~np.concatenate(
        [sane[keep_rows], np.ones(clone_rows.size + parents.size, bool)])
    prune |= np.concatenate([victim[keep_rows], np.zeros(clone_rows.size + parents.size, bool)])
    if prune_big:
        new_max_scale = np.concatenate([max_scale[keep_rows], max_scale[clone_rows],
                                        spatial_size(covariance_4d(Gaussians(**child))) if parents.size
                                        else np.zeros(0)])
        prune |= radius_known > cfg.prune_screen_size
        prune |= new_max_scale > cfg.prune_world_size * extent
    alive = ~prune
    out = Gaussians(**{n: a[alive] for n, a in new.items()})
    if stats is not None:
        stats.update(cloned=int(clone_rows.size), split=int(split_rows.size), pruned=int(prune.sum()),
                     replaced=int(victim.sum()), is_new=is_new[alive])
    return out, source[alive]


def moment_source_index(source_index: np.ndarray, is_new: np.ndarray) -> np.ndarray:
    """source_index with -1 on new rows: what DeviceAdam.remap needs to zero their moments."""
    return np.where(np.asarray(is_new, bool), -1, np.asarray(source_index)).astype(np.int64)
