"""The rasterizers' scalar helpers that decide skips (cl/blend.h), built into a test kernel:
ln_upper bounds ln from above by at most 1.5e-3, so skip_threshold never lies above the exact
log(ALPHA_MIN / opac) - SKIP_MARGIN (a skip it makes, the exact test would make too).  And the
four rasterizer kernels share that header, not each other's files."""
from __future__ import annotations

import re

import numpy as np
import pyopencl.array as cla
import pytest

from conftest import small
from endowave_cl.layout import ALPHA_MIN
from endowave_cl.ops.rasterize import _options
from endowave_cl.runtime import kernel_dir

SOURCE = """
#include "blend.h"
__kernel void helpers(__global const float *x, __global const float *opac, const int n,
                      __global float *ln_up, __global float *thr) {
    const int i = get_global_id(0);
    if (i >= n) return;
    ln_up[i] = ln_upper(x[i]);
    thr[i] = skip_threshold(opac[i]);
}
"""


@pytest.mark.oclgrind
def test_ln_upper_and_skip_threshold_bound_the_exact_log(rt):
    rng = np.random.default_rng(0)
    # [1, 2) densely, every power of two and its neighbours (the exponent's steps), and [1, 1e6)
    dense = small(100_000, 500)
    pows = np.float32(2.0) ** np.arange(0, 20, dtype=np.float32)
    x = np.concatenate([np.linspace(1, 2, dense + 1, dtype=np.float32)[:-1], pows,
                        np.nextafter(pows, np.float32(np.inf)), np.nextafter(pows[1:], np.float32(0)),
                        np.exp(rng.uniform(0, np.log(1e6), dense)).astype(np.float32)]).astype(np.float32)
    opac = np.concatenate([rng.uniform(0.0, 1.0, x.size - 4), [0.0, ALPHA_MIN, np.nextafter(np.float32(ALPHA_MIN), 0),
                                                               1.0]]).astype(np.float32)
    prg = rt.program("rasterize.cl", _options(6), source=SOURCE)
    q = rt.queue
    d_x, d_o = cla.to_device(q, x), cla.to_device(q, opac)
    ln_up, thr = cla.empty(q, x.size, np.float32), cla.empty(q, x.size, np.float32)
    prg.helpers(q, (x.size,), None, d_x.data, d_o.data, np.int32(x.size), ln_up.data, thr.data)
    over = ln_up.get().astype(np.float64) - np.log(x.astype(np.float64))
    assert over.min() > 0 and over.max() < 1.5e-3, (over.min(), over.max())
    t = thr.get().astype(np.float64)
    keep = opac >= np.float32(ALPHA_MIN)
    exact = np.log(np.float64(np.float32(ALPHA_MIN)) / opac[keep].astype(np.float64)) - 1e-3
    assert np.all(t[keep] <= exact) and np.all(t[keep] > exact - 1.6e-3)
    assert np.all(np.isinf(t[~keep]) & (t[~keep] > 0))


RASTER_KERNELS = ("rasterize.cl", "rasterize_bwd.cl", "rasterize_vec.cl", "rasterize_vec_bwd.cl")
_INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"', re.MULTILINE)


def _includes(path):
    return _INCLUDE.findall(path.read_text())


def test_no_kernel_file_includes_another_kernel_file():
    """Shared kernel code lives in headers: no .cl (or .h) file includes a .cl file (issue 59)."""
    kdir = kernel_dir()
    bad = {p.name: inc for p in sorted(kdir.iterdir()) if p.suffix in (".cl", ".h")
           for inc in _includes(p) if inc.endswith(".cl")}
    assert not bad, f"kernel files that include a .cl file (move the shared code to a header): {bad}"


def test_the_four_rasterizers_share_one_blend_header():
    """The blend step, the skip and the cull helpers are written once, in blend.h, which all four
    rasterizer kernels include; the kernels do not write the power or the alpha clamp themselves."""
    kdir = kernel_dir()
    for name in RASTER_KERNELS:
        text = (kdir / name).read_text()
        assert "blend.h" in _includes(kdir / name), name
        for own in ("cop.y * dx * dy", "cop.y * d.x * d.y", "? raw : ", "inline float skip_threshold",
                    "inline float4 cull_box"):
            assert own not in text, f"{name} writes {own!r} itself: use blend.h"
