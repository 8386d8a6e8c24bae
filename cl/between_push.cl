/* The in-between target's reversed splats of two frames, blended (endowave_cl/ops/between.py
 * between_push; reference: endowave_cl/reference/between.py between_push_ref, the host path
 * train/between.py reversed_splat_interpolation).
 *
 * acc0, acc1 [H, W, 3]: between_splat's fixed-point sums (reach, reach x back) of frame 0's and
 * frame 1's paths.  Per pixel q and frame f: reach_f = the summed weight; back_f = the summed
 * displacement / reach_f where reach_f > SPLAT_MIN_WEIGHT (else 0), where q's colour comes from;
 * pushed_f = img_f ([H, W, 4], its colour) sampled at q + back_f (between_sample.h: bicubic, or
 * Lanczos-4 with -DLANCZOS4), clipped to [lo_f, hi_f].
 * out [H, W, 3] = (sum_f a_f min(reach_f, 1) pushed_f) / (sum_f a_f min(reach_f, 1)) over the
 * frames with reach_f > SPLAT_MIN_WEIGHT (a_0 = wa = 1 - s, a_1 = wb = s), or fill where that sum
 * is not above SPLAT_MIN_WEIGHT.  No adjoint. */
#pragma OPENCL FP_CONTRACT OFF

#include "between_sample.h"

inline float from_fixed(const long v) { return convert_float_rte(v) * (1.0f / (float)(1L << SPLAT_FRAC_BITS)); }

__kernel void between_push(__global const long *acc0, __global const long *acc1,
                           __global const float4 *img0, __global const float4 *img1,
                           const float lo0, const float hi0, const float lo1, const float hi1,
                           const float wa, const float wb, const int W, const int H,
                           __global const float *fill, __global float *out) {
    const int i = get_global_id(0);
    if (i >= W * H) return;
    const int x = i % W, y = i / W;
    float3 image = (float3)(0.0f);
    float total = 0.0f;
    for (int f = 0; f < 2; ++f) {
        __global const long *acc = (f ? acc1 : acc0) + 3 * i;
        const float reach = from_fixed(acc[0]);
        const int ok = reach > SPLAT_MIN_WEIGHT;
        const float2 back = ok ? (float2)(from_fixed(acc[1]) / reach, from_fixed(acc[2]) / reach) : (float2)(0.0f);
        float3 pushed = sample_rgbm(f ? img1 : img0, W, H, (float)x + back.x, (float)y + back.y).xyz;
        pushed = f ? clamp(pushed, lo1, hi1) : clamp(pushed, lo0, hi0);
        const float wt = ok ? (f ? wb : wa) * (reach < 1.0f ? reach : 1.0f) : 0.0f;
        image += (float3)(wt) * pushed;
        total += wt;
    }
    vstore3(total > SPLAT_MIN_WEIGHT ? image / total : vload3(i, fill), i, out);
}
