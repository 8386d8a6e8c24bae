"""numpy references of cl/adam.cl (torch.optim.Adam's update, per-element learning rates) and
cl/opacity_reset.cl (the 3DGS opacity reset)."""
from __future__ import annotations

import numpy as np


def adam_step_ref(param: np.ndarray, grad: np.ndarray, exp_avg: np.ndarray, exp_avg_sq: np.ndarray,
              lr: np.ndarray, step: int, beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-15):
    """One Adam step of one group in float64; returns (param, exp_avg, exp_avg_sq) as float32.

    lr: per-element learning rate, same shape as param (elements with lr 0 are left as they are,
    moments included).  step: the step number after this update (1 for the first).
    """
    p, g = param.astype(np.float64), grad.astype(np.float64)
    m, v = exp_avg.astype(np.float64), exp_avg_sq.astype(np.float64)
    lr = np.broadcast_to(np.asarray(lr, np.float64), p.shape)
    live = lr != 0
    m_new = beta1 * m + (1 - beta1) * g
    v_new = beta2 * v + (1 - beta2) * g * g
    bc1 = 1 - beta1 ** step
    bc2 = 1 - beta2 ** step
    p_new = p - (lr / bc1) * m_new / (np.sqrt(v_new) / np.sqrt(bc2) + eps)
    f32 = lambda new, old: np.where(live, new, old).astype(np.float32)
    return f32(p_new, p), f32(m_new, m), f32(v_new, v)


def opacity_reset_ref(opacity: np.ndarray, cap: float) -> np.ndarray:
    """The 3DGS opacity reset: min(opacity, cap) as float32 [N] (logits; cap = logit of the value)."""
    return np.minimum(np.asarray(opacity, np.float32), np.float32(cap))
