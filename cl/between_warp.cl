/* The in-between target's backward warp (endowave_cl/ops/between.py between_warp; reference:
 * endowave_cl/reference/between.py between_warp_ref, the host path train/between.py _warp_pair).
 *
 * Two frames img0, img1 [H, W, 4] (RGB and tool mask: ops/between.py frame_on_device) are sampled at p - g0(p) and p - g1(p), where each path
 * g [H, W, 2] is ca A + cb B (the second term only with nb = 1; A, B read with a per-pixel pitch
 * and a channel offset, so that a render's flow channels serve as they lie in its feature image).
 * As OpenCV's remap (which the host path calls): the border is replicated, the frames' colour is
 * sampled bicubically (a = -0.75; Lanczos-4 when built with -DLANCZOS4: between_sample.h) and
 * clipped to [lo, hi], each frame's own range, the tool masks bilinearly.
 *
 * Outputs per pixel: blend [H, W, 3] = wa W0 + wb W1 (wa = 1 - s and wb = s, rounded on the host); diff [H, W] = sum_c |W0 - W1|;
 * ok [H, W] = 1 where both warped masks exceed 0.5 (a frame without a mask counts as tissue).
 * No adjoint: the target is a constant of the loss. */
#pragma OPENCL FP_CONTRACT OFF

#include "between_sample.h"   /* remap's sampling: bicubic (or Lanczos-4) colour, bilinear mask; paths */

__kernel void between_warp(__global const float4 *img0, __global const float4 *img1,
                           const float lo0, const float hi0, const float lo1, const float hi1,
                           const int has_mask0, const int has_mask1,
                           __global const float *a0, const int pa0, const int oa0, const float ca0,
                           __global const float *b0, const int pb0, const int ob0, const float cb0, const int nb0,
                           __global const float *a1, const int pa1, const int oa1, const float ca1,
                           __global const float *b1, const int pb1, const int ob1, const float cb1, const int nb1,
                           const int W, const int H, const float wa, const float wb,
                           __global float *blend, __global float *diff, __global float *ok) {
    const int i = get_global_id(0);
    if (i >= W * H) return;
    const int x = i % W, y = i / W;
    const float2 g0 = path_at(a0, pa0, oa0, ca0, b0, pb0, ob0, cb0, nb0, i);
    const float2 g1 = path_at(a1, pa1, oa1, ca1, b1, pb1, ob1, cb1, nb1, i);
    const float4 s0 = sample_rgbm(img0, W, H, (float)x + (-g0.x), (float)y + (-g0.y));
    const float4 s1 = sample_rgbm(img1, W, H, (float)x + (-g1.x), (float)y + (-g1.y));
    const float3 w0 = clamp(s0.xyz, lo0, hi0);     /* the cubic kernel overshoots at edges */
    const float3 w1 = clamp(s1.xyz, lo1, hi1);
    const int good = (!has_mask0 || s0.w > 0.5f) && (!has_mask1 || s1.w > 0.5f);
    vstore3(w0 * wa + w1 * wb, i, blend);
    const float3 d = fabs(w0 - w1);
    diff[i] = d.x + d.y + d.z;
    ok[i] = good ? 1.0f : 0.0f;
}
