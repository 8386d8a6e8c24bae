/* The in-between target's forward splat of a path (endowave_cl/ops/between.py between_splat;
 * reference: endowave_cl/reference/between.py between_splat_ref, the host path
 * warp.splat_forward(-g, g, weight) inside train/between.py reversed_splat).
 *
 * Every pixel p with g = ca A (+ cb B) (g [H, W, 2], read as between_sample.h path_at) lands at
 * p + g and is shared among the four pixels around it with bilinear weights w (float products, as
 * the host's), times its source weight (0 on a tool pixel: the frame img [H, W, 4]'s mask channel
 * <= 0.5, with has_mask).  Per
 * target pixel the kernel sums (w, -w g.x, -w g.y) into acc [H, W, 3] as 64-bit fixed point (units
 * of 2^-SPLAT_FRAC_BITS, each term rounded to the nearest unit, saturated): integer atomic sums
 * are the same in every order, so the splat is deterministic on every device.  Non-finite paths
 * reach nothing.  acc must be zero before the launch.  No adjoint: the target is a constant of the
 * loss.  Needs cl_khr_int64_base_atomics. */
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
#pragma OPENCL FP_CONTRACT OFF

#include "between_sample.h"

inline void splat_add(volatile __global long *acc, const float w, const float2 g) {
    const float unit = (float)(1L << SPLAT_FRAC_BITS);
    atom_add(acc, convert_long_sat_rte(w * unit));
    atom_add(acc + 1, convert_long_sat_rte((w * -g.x) * unit));
    atom_add(acc + 2, convert_long_sat_rte((w * -g.y) * unit));
}

__kernel void between_splat(__global const float *a, const int pa, const int oa, const float ca,
                            __global const float *b, const int pb, const int ob, const float cb, const int nb,
                            __global const float4 *img, const int has_mask, const int W, const int H,
                            volatile __global long *acc) {
    const int i = get_global_id(0);
    if (i >= W * H) return;
    if (has_mask && !(img[i].w > 0.5f)) return;
    const float2 g = path_at(a, pa, oa, ca, b, pb, ob, cb, nb, i);
    const float x = (float)(i % W) + g.x, y = (float)(i / W) + g.y;
    if (!(isfinite(x) && isfinite(y))) return;
    const float x0 = floor(x), y0 = floor(y);
    /* the corner (x0, y0) must lie in [-1, W - 1] x [-1, H - 1] for any corner to land */
    if (!(x0 >= -1.0f && x0 <= (float)(W - 1) && y0 >= -1.0f && y0 <= (float)(H - 1))) return;
    const float fx = x - x0, fy = y - y0, gx = 1.0f - fx, gy = 1.0f - fy;
    const int ix = (int)x0, iy = (int)y0;
    if (iy >= 0) {
        if (ix >= 0) splat_add(acc + 3 * (iy * W + ix), gx * gy, g);
        if (ix + 1 < W) splat_add(acc + 3 * (iy * W + ix + 1), fx * gy, g);
    }
    if (iy + 1 < H) {
        if (ix >= 0) splat_add(acc + 3 * ((iy + 1) * W + ix), gx * fy, g);
        if (ix + 1 < W) splat_add(acc + 3 * ((iy + 1) * W + ix + 1), fx * fy, g);
    }
}
