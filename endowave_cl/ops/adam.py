"""Adam on the device: one kernel launch (cl/adam.cl) updates all seven parameter groups.

Learning rates (``lrs``), one float per key:
    means     x, y, z columns of means [N, 4] (the decayed position lr, see position_lr)
    means_t   t column of means (default: lrs["means"]); the trainer passes the initial
              position lr here, not decayed (DESIGN.md: "t as initial position lr")
    scales    the first three log-stds of scales [N, 4] (the principal axes labelled x, y, z)
    scales_t  the fourth (the axis labelled t, a Gaussian's lifetime before rotation; default:
              lrs["scales"])
    quat_l, quat_r, opacity, phase   one lr per group
    sh        the DC coefficient of the n = 0 temporal term, sh[:, 0, 0, :]
    sh_rest   every other TEASH coefficient (default: lrs["sh"] / SH_REST_DIVISOR), i.e.
              3DGS's "higher orders / 20" extended to the temporal terms n >= 1
A group (or part of one) whose lr is 0 is frozen: its parameters and moments are untouched.
``step(..., visible=radius)`` freezes the same way every row of a Gaussian whose projected radius
is 0 this step (culled at the step's time: its gradient is 0), as gsplat's SelectiveAdam: a 4D
Gaussian outside its lifetime keeps its parameters and moments instead of drifting on momentum.

Moments are kept on the device; ``state_dict`` / ``load_state_dict`` move them as numpy, and
``remap`` rebuilds them after densification (row i <- old row source_index[i], zeros where < 0).
"""
from __future__ import annotations

import math
from typing import Dict, Mapping, Optional, Tuple

import numpy as np
import pyopencl.array as cla

from ..errors import EndowaveError
from ..gaussians import PARAM_NAMES

BETA1 = 0.9
BETA2 = 0.999
ADAM_EPS = 1e-15          # 3DGS / 4DGS use 1e-15 instead of torch's 1e-8
SH_REST_DIVISOR = 20.0    # 3DGS: feature_lr / 20 for every SH coefficient but the DC term
SH_DC_ELEMENTS = 3        # sh[:, 0, 0, :] is the first 3 floats of a Gaussian's sh row
MEANS_XYZ_COLUMNS = 3     # means[:, :3] spatial, means[:, 3] time
SCALES_XYZ_COLUMNS = 3    # scales[:, :3] the axes labelled x, y, z, scales[:, 3] the one labelled t
WORK_GROUP = 64
ADAM_RUN = 8              # consecutive elements per work-item (ADAM_RUN in cl/adam.cl)
MAX_ELEMENTS = 2 ** 31 - 1  # the kernel indexes with int


def sh_gaussians_per_item(ncoef: int) -> int:
    """Gaussians per work-item of Adam's factored sh group (SH_GPW in cl/adam.cl): the fewest whose
    rows of ncoef floats fill whole runs of ADAM_RUN, when that block is at most 128 floats, else 1."""
    gpw = ADAM_RUN // math.gcd(max(int(ncoef), 1), ADAM_RUN)
    return gpw if gpw * ncoef <= 128 else 1


def position_lr(step: int, max_steps: int, init: float = 1.6e-4, final: float = 1.6e-6,
                extent: float = 1.0) -> float:
    """3DGS's exponential (log-linear) position lr schedule times the scene extent.

    lr(step) = exp((1 - u) log(init) + u log(final)) * extent, u = clip(step / max_steps, 0, 1).
    """
    if max_steps <= 0:
        u = 1.0
    else:
        u = min(max(step / float(max_steps), 0.0), 1.0)
    if init <= 0 or final <= 0:
        return 0.0  # log-linear interpolation is undefined: treat a zero end as "frozen"
    return float(math.exp((1.0 - u) * math.log(init) + u * math.log(final)) * extent)


def anneal_factor(step: int, start: int, end: int, final: float) -> float:
    """1 until ``start``, then log-linear to ``final`` at ``end`` (and ``final`` after it)."""
    if final == 1.0 or step <= start:
        return 1.0
    u = 1.0 if end <= start else min((step - start) / float(end - start), 1.0)
    return float(math.exp(u * math.log(final)))


def group_lr_layout(name: str, shape: Tuple[int, ...], lrs: Mapping[str, float]) -> Tuple[int, int, float, float]:
    """(row_len, split, lr_a, lr_b) of a group: element j uses lr_a when j % row_len < split."""
    row = int(np.prod(shape[1:])) if len(shape) > 1 else 1
    try:
        if name == "means":
            lr = float(lrs["means"])
            return row, MEANS_XYZ_COLUMNS, lr, float(lrs.get("means_t", lr))
        if name == "scales":
            lr = float(lrs["scales"])
            return row, SCALES_XYZ_COLUMNS, lr, float(lrs.get("scales_t", lr))
        if name == "sh":
            lr = float(lrs["sh"])
            return row, SH_DC_ELEMENTS, lr, float(lrs.get("sh_rest", lr / SH_REST_DIVISOR))
        lr = float(lrs[name])
    except KeyError as e:
        raise EndowaveError(f"Adam: no learning rate for parameter group {e.args[0]!r}") from None
    return row, row, lr, lr


def element_lrs(name: str, shape: Tuple[int, ...], lrs: Mapping[str, float]) -> np.ndarray:
    """Per-element lr of a group, same shape as the group (for references and tests)."""
    row, split, lra, lrb = group_lr_layout(name, shape, lrs)
    n = int(np.prod(shape))
    col = np.arange(n) % max(row, 1)
    return np.where(col < split, lra, lrb).astype(np.float32).reshape(shape)


def opacity_reset(rt, opacity, cap: float) -> None:
    """In place: opacity [N] float32 (logits) = min(opacity, cap), cap the logit of the reset value
    (cl/opacity_reset.cl; reference: reference/adam.py opacity_reset_ref).  The trainer zeroes the
    opacity group's moments with DeviceAdam.reset_moments beside it, as 3DGS does."""
    n = int(opacity.size)
    if n == 0:
        return
    if opacity.dtype != np.float32 or not opacity.flags.c_contiguous:
        raise EndowaveError(f"opacity_reset: opacity must be C-contiguous float32, got {opacity.dtype}")
    rt.launch_1d(rt.kernel("opacity_reset.cl", "opacity_reset"), n, WORK_GROUP, opacity.data, np.float32(cap),
                 np.int32(n))


class DeviceAdam:
    """Adam over the seven parameter groups, one kernel launch per step."""

    def __init__(self, rt, params: Dict[str, "object"], lrs: Mapping[str, float],
                 betas: Tuple[float, float] = (BETA1, BETA2), eps: float = ADAM_EPS):
        self.rt = rt
        self._cla = cla
        self.betas = (float(betas[0]), float(betas[1]))
        self.eps = float(eps)
        self.lrs: Dict[str, float] = {k: float(v) for k, v in lrs.items()}
        self.step_count = 0
        self._check_params(params)
        self.params = dict(params)
        self.exp_avg = {n: self._zeros(params[n].shape) for n in PARAM_NAMES}
        self.exp_avg_sq = {n: self._zeros(params[n].shape) for n in PARAM_NAMES}
        for n in PARAM_NAMES:  # fail early on a missing lr
            group_lr_layout(n, params[n].shape, self.lrs)

    # -- helpers ------------------------------------------------------------------------------
    def _zeros(self, shape):
        return self._cla.zeros(self.rt.queue, shape, np.float32)

    @staticmethod
    def _check_params(params) -> None:
        missing = [n for n in PARAM_NAMES if n not in params]
        if missing:
            raise EndowaveError(f"Adam: missing parameter groups {missing}")
        for n in PARAM_NAMES:
            if params[n].dtype != np.float32:
                raise EndowaveError(f"Adam: parameter {n!r} must be float32, got {params[n].dtype}")

    def _buf(self, arr):
        return self.rt.buf(arr)   # zero-size pyopencl arrays have no buffer: the runtime's placeholder

    # -- the update ---------------------------------------------------------------------------
    def step(self, grads: Mapping[str, "object"], lrs: Optional[Mapping[str, float]] = None,
             visible=None, rows=None, skip=None) -> None:
        """One Adam step; ``lrs`` (optional) updates some learning rates first and is kept.
        grads["sh"] may be an ops.project.ShGradFactors (render_backward(..., sh_factors=True)):
        the kernel forms the SH gradient from its factors, the same values as the full array.
        visible: None, or an int32 device array [N] (the step's projected radius): rows where it
        is 0 are left untouched, parameters and moments.
        rows: None, or an int32 device array [L] of row indices (ops.select.LiveRows.rows): the
        gradients (and visible) are then compact, [L, ...], row i of them belonging to parameter
        row rows[i]; every other row is left untouched (cl/adam.cl adam_step_rows).
        skip: None, or the step gate, an int32 device array [1] (ops.util.step_gate): where it is
        not 0 when the kernel runs nothing changes.  The step is counted here all the same (the
        bias corrections of later steps): the caller that finds it skipped sets step_count back."""
        if lrs:
            self.lrs.update({k: float(v) for k, v in lrs.items()})
        n_rows = int(self.params["means"].shape[0])
        n_grad = n_rows if rows is None else int(rows.shape[0])
        if rows is not None and (rows.dtype != np.int32 or len(rows.shape) != 1 or n_grad > n_rows):
            raise EndowaveError(f"Adam: rows must be int32 [L] with L <= {n_rows}, got {tuple(rows.shape)} {rows.dtype}")
        if visible is not None and (tuple(visible.shape) != (n_grad,) or visible.dtype != np.int32):
            raise EndowaveError(f"Adam: visible must be int32 [{n_grad}], got {tuple(visible.shape)} {visible.dtype}")
        step = self.step_count + 1  # counted once the arguments are valid
        b1, b2 = self.betas
        inv_bc1 = 1.0 / (1.0 - b1 ** step)
        inv_sqrt_bc2 = 1.0 / math.sqrt(1.0 - b2 ** step)
        args = []
        options = []   # adam.cl build options
        total = runs = 0
        for n in PARAM_NAMES:
            p = self.params[n]
            row, split, lra, lrb = group_lr_layout(n, p.shape, self.lrs)
            count = n_grad * max(row, 1) if p.size else 0
            factored = False
            g = grads.get(n) if hasattr(grads, "get") else grads[n]
            if g is None:
                if count and (lra != 0.0 or lrb != 0.0):
                    raise EndowaveError(f"Adam: no gradient for parameter group {n!r} (lr is not 0)")
                count = 0  # nothing to update in this group
                gbuf = self.rt.dummy_buffer()
            else:
                want = (n_grad,) + tuple(p.shape[1:])
                if tuple(g.shape) != want or g.dtype != np.float32:
                    raise EndowaveError(f"Adam: gradient of {n!r} has shape {tuple(g.shape)} {g.dtype}, "
                                        f"expected {want} float32")
                factored = n == "sh" and hasattr(g, "factors")   # ops.project.ShGradFactors
                if factored:
                    options = ["-DADAM_SH_FACTORS", f"-DSH_DEGREE={int(round(math.sqrt(g.K))) - 1}",
                               f"-DNT={g.nt}"]
                gbuf = self._buf(g.factors if factored else g)
            if rows is None:
                args += [self._buf(p), gbuf, self._buf(self.exp_avg[n]), self._buf(self.exp_avg_sq[n]),
                         np.int32(count), np.int32(max(row, 1)), np.int32(split),
                         np.float32(lra), np.float32(lrb)]
            else:   # row 0: the group is left alone (adam_step_rows)
                args += [self._buf(p), gbuf, self._buf(self.exp_avg[n]), self._buf(self.exp_avg_sq[n]),
                         np.int32(max(row, 1) if count else 0), np.int32(split), np.float32(lra), np.float32(lrb)]
            total += count
            # a factored sh gradient: sh_gaussians_per_item Gaussians per work-item (cl/adam.cl adam_sh_block)
            runs += -(-(count // max(row, 1)) // sh_gaussians_per_item(row)) if factored else -(-count // ADAM_RUN)
        size = sum(int(self.params[n].size) for n in PARAM_NAMES)
        if size > MAX_ELEMENTS:
            raise EndowaveError(f"Adam: {size} parameters exceed the kernel's int index range")
        self.step_count = step
        if total == 0:
            return
        args += [np.float32(b1), np.float32(b2), np.float32(1.0 - b1), np.float32(1.0 - b2), np.float32(self.eps),
                 np.float32(inv_bc1), np.float32(inv_sqrt_bc2)]
        vis = [self.rt.dummy_buffer() if visible is None else self._buf(visible), np.int32(visible is not None),
               self.rt.buf(skip), np.int32(skip is not None)]
        if rows is None:
            self.rt.launch_1d(self.rt.kernel("adam.cl", "adam_step", options), runs, WORK_GROUP, *args, *vis)
        else:
            self.rt.launch_1d(self.rt.kernel("adam.cl", "adam_step_rows", options), n_grad, WORK_GROUP, *args,
                              np.int32(n_grad), rows.data, *vis)

    def reset_moments(self, name: str) -> None:
        """Zero one group's moments (3DGS does this for opacity at an opacity reset)."""
        self.exp_avg[name] = self._zeros(self.params[name].shape)
        self.exp_avg_sq[name] = self._zeros(self.params[name].shape)

    # -- state ----------------------------------------------------------------------------------
    def state_dict(self) -> Dict[str, object]:
        return {"step": int(self.step_count),
                "exp_avg": {n: self.exp_avg[n].get() for n in PARAM_NAMES},
                "exp_avg_sq": {n: self.exp_avg_sq[n].get() for n in PARAM_NAMES}}

    def load_state_dict(self, state: Mapping[str, object]) -> None:
        try:
            step = int(state["step"])
            ea, eas = state["exp_avg"], state["exp_avg_sq"]
            new_ea, new_eas = {}, {}
            for n in PARAM_NAMES:
                shape = tuple(self.params[n].shape)
                for src, dst, what in ((ea, new_ea, "exp_avg"), (eas, new_eas, "exp_avg_sq")):
                    a = np.ascontiguousarray(src[n], dtype=np.float32)
                    if a.shape != shape:
                        raise EndowaveError(f"Adam state: {what}[{n!r}] has shape {a.shape}, "
                                            f"parameter has {shape}")
                    dst[n] = self._cla.to_device(self.rt.queue, a) if a.size else self._zeros(shape)
        except KeyError as e:
            raise EndowaveError(f"Adam state: missing entry {e.args[0]!r}") from None
        self.step_count = step
        self.exp_avg, self.exp_avg_sq = new_ea, new_eas

    def remap(self, params: Dict[str, "object"], source_index: np.ndarray) -> None:
        """Follow densification: new row i takes old row source_index[i]'s moments, zeros if < 0."""
        self._check_params(params)
        src = np.asarray(source_index).astype(np.int64).reshape(-1)
        n_new = int(params["means"].shape[0])
        n_old = int(self.params["means"].shape[0])
        if src.shape[0] != n_new:
            raise EndowaveError(f"Adam remap: source_index has {src.shape[0]} rows, parameters {n_new}")
        if src.size and src.max() >= n_old:
            raise EndowaveError(f"Adam remap: source_index refers to row {src.max()} of {n_old}")
        keep = src >= 0
        state = self.state_dict()
        for key in ("exp_avg", "exp_avg_sq"):
            for n in PARAM_NAMES:
                old = state[key][n]
                new = np.zeros((n_new,) + old.shape[1:], np.float32)
                new[keep] = old[src[keep]]
                state[key][n] = new
        self.params = dict(params)
        self.load_state_dict(state)
