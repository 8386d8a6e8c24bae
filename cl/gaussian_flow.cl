/* Per-Gaussian flow loss and its gradient: every visible Gaussian's own 2D flow (the displacement
 * of its projected conditional mean from t to t_flow, features[i, CH_FLOW..CH_FLOW+1] of
 * project4d) against the pseudo ground-truth flow at the pixel under its projected centre.
 *
 * Why: the image flow loss (image_loss.cl) supervises the composited flow, a weighted mean over
 * the Gaussians of a pixel, so Gaussians whose velocities scatter around the right mean cost it
 * nothing; at a time between training frames those Gaussians part and the render blurs.  This
 * term gives each Gaussian the flow of the tissue it sits on.
 *
 *   loss = coef * sum_i w_i rho(|f_i - g(p_i)|),  rho = the image flow loss's Huber (|e|^2, continued
 *          as 2 delta |e| - delta^2 beyond delta)
 *   w_i  = opac_i * flow_w(p_i) * [depth_i <= (1 + depth_tol) * D(p_i) / A(p_i)]
 * p_i = the pixel holding means2d_i (pixel (x, y) covers [x, x + 1) x [y, y + 1)); D, A: the rendered
 * depth channel and alpha (D / A: the surface depth there); opac_i = sigmoid(opacity) * marginal
 * at t.  w_i is held fixed (no gradient through the weight or through p_i): the term moves only
 * the Gaussian's own flow, v_features[i, CH_FLOW + k] += coef * w_i * rho'(e)_k; it is written
 * (not accumulated) by work-item i alone.  Culled Gaussians (radius 0), centres outside the image
 * and pixels without a trusted flow (flow_w = 0) contribute nothing.
 * Reference: endowave_cl/reference/losses.py::gaussian_flow_loss_ref.  Host side:
 * endowave_cl/train/device_losses.py::gaussian_flow_enqueue.  OpenCL C 1.2. */
#include "common.h"

/* The channel layout comes from the host (endowave_cl/layout.py), defined there once. */
#if !defined(C) || !defined(CF) || !defined(CH_DEPTH) || !defined(CH_FLOW)
#error "build with -DC, -DCF, -DCH_DEPTH and -DCH_FLOW (train/device_losses.py::gaussian_flow_enqueue)"
#endif

__kernel void gaussian_flow_loss(const int n,
                                 __global const float *means2d,   /* [N, 2] */
                                 __global const float *opac,      /* [N] */
                                 __global const int *radius,      /* [N] */
                                 __global const float *depth,     /* [N] camera-space z */
                                 __global const float *features,  /* [N, C] */
                                 __global const float *render,    /* [H, W, CF] composited channels */
                                 __global const float *alpha,     /* [H, W] */
                                 __global const float *flow_gt,   /* [H, W, 2] */
                                 __global const float *flow_w,    /* [H, W] */
                                 const int width, const int height,
                                 const float coef, const float delta, const float depth_tol,
                                 __global float *v_features,      /* [N, C]: flow channels written */
                                 __global float *partial,         /* [groups]: sum of w_i rho_i */
                                 __local float *scratch) {        /* [local size] */
    const int i = get_global_id(0);
    const int lid = get_local_id(0), lsize = get_local_size(0);
    float sum = 0.0f;
    if (i < n) {
        float v0 = 0.0f, v1 = 0.0f;
        const float x = means2d[2 * i], y = means2d[2 * i + 1];
        if (radius[i] > 0 && x >= 0.0f && y >= 0.0f && x < (float)width && y < (float)height) {
            const int p = (int)y * width + (int)x;
            const float a = alpha[p];
            const float surface = a > 0.0f ? render[(size_t)p * CF + CH_DEPTH] / a : 0.0f;
            float w = opac[i] * flow_w[p];
            if (!(a > 0.0f && depth[i] <= (1.0f + depth_tol) * surface)) w = 0.0f;
            if (w > 0.0f) {
                const float e0 = features[(size_t)i * C + CH_FLOW] - flow_gt[2 * p];
                const float e1 = features[(size_t)i * C + CH_FLOW + 1] - flow_gt[2 * p + 1];
                const float n2 = e0 * e0 + e1 * e1;
                float scale = 2.0f;                    /* d rho / d e = scale * e */
                if (n2 <= delta * delta) {
                    sum = w * n2;
                } else {
                    const float nrm = sqrt(n2);
                    sum = w * (2.0f * delta * nrm - delta * delta);
                    scale = 2.0f * delta / nrm;
                }
                v0 = coef * w * scale * e0;
                v1 = coef * w * scale * e1;
            }
        }
        for (int c = 0; c < C; ++c)
            v_features[(size_t)i * C + c] = (c == CH_FLOW) ? v0 : (c == CH_FLOW + 1) ? v1 : 0.0f;
    }
    scratch[lid] = sum;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int s = lsize / 2; s > 0; s >>= 1) {
        if (lid < s) scratch[lid] += scratch[lid + s];
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    if (lid == 0) partial[get_group_id(0)] = scratch[0];
}
