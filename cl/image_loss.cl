/* The training step's image losses on the device: masked L1 + D-SSIM of the colour, L1 of the
 * depth, squared endpoint error of the flow, and their gradient with respect to the rendered
 * feature image.  The same functions as endowave_cl/train/losses.py (the torch reference, whose
 * module doc gives the choices); host side endowave_cl/train/device_losses.py.  OpenCL C 1.2.
 *
 * Images are channel-last.  feat [npix, CF]: the rendered channels, colour in 0..2, depth in
 * CH_DEPTH, flow in CH_FLOW, CH_FLOW + 1 (build options -DCF, -DCH_DEPTH, -DCH_FLOW).
 * The weight maps are per-frame constants the host prepares: mask [npix] (1 = supervise, all ones
 * without a tool mask), depth_w = (gt depth > 0) * mask, flow_w = consistency mask * mask.
 *
 * SSIM (3DGS's: 11 x 11 Gaussian window, zero padding, C1 = 0.01^2, C2 = 0.03^2) runs as
 *   ssim_target_stack -> the target's two maps (y m, (y m)^2), 6 ch., blurred once per frame
 *                        when the targets are uploaded (they do not change between steps)
 *   ssim_stack  -> the three maps that involve the render (x m, (x m)^2, x m y m), 9 ch.
 *   blur        -> conv_axis (cl/wavelet.cl) along W then H with border "zero"
 *   image_loss_terms -> per-pixel loss sums and gradients; dL/d(mu_x, E[xx], E[xy]) per channel
 *   blur adjoint     -> the same convolutions with the reversed window
 *   ssim_grad_combine -> back through the three maps to the colour channels (and the wavelet
 *                        term's colour gradient added in the same pass).
 * With S = A1 A2 / (B1 B2), A1 = 2 mx my + C1, A2 = 2 sxy + C2, B1 = mx^2 + my^2 + C1,
 * B2 = sxx + syy + C2 (sxx = exx - mx^2, syy = eyy - my^2, sxy = exy - mx my):
 *   dS/dmx = 2 my (A2 - A1) / (B1 B2) - 2 mx S (B2 - B1) / (B1 B2)
 *   dS/dexx = -S / B2,  dS/dexy = 2 A1 / (B1 B2).
 */
#include "common.h"

#ifndef CF
#define CF 6
#endif
#ifndef CH_DEPTH
#define CH_DEPTH 3
#endif
#ifndef CH_FLOW
#define CH_FLOW 4
#endif
#define SSIM_C1 (0.01f * 0.01f)
#define SSIM_C2 (0.03f * 0.03f)
#define NMAP 9           /* ssim_stack channels: 3 maps (x m, (x m)^2, x m y m) x 3 colours, map-major */
#define NTMAP 6          /* ssim_target_stack channels: 2 maps (y m, (y m)^2) x 3 colours */
#define NGRAD 9          /* SSIM gradient maps: d/d mu_x, d/d E[xx], d/d E[xy], x 3 colours */
#define NSUM 5           /* partial sums: |x - y| m, S m, |d - d_gt| w, Huber(|f - f_gt|) w, (x - y)^2 m */

/* stack[p, map * 3 + c] for the three SSIM maps of the masked colours that involve the render. */
__kernel void ssim_stack(__global const float *feat,   /* [npix, CF] */
                         __global const float *gt,     /* [npix, 3] */
                         __global const float *mask,   /* [npix] */
                         const int npix,
                         __global float *stack) {      /* [npix, NMAP] */
    const int p = get_global_id(0);
    if (p >= npix) return;
    const float m = mask[p];
    __global float *s = stack + (size_t)p * NMAP;
#pragma unroll
    for (int c = 0; c < 3; c++) {
        const float x = feat[(size_t)p * CF + c] * m, y = gt[p * 3 + c] * m;
        s[c] = x;
        s[3 + c] = x * x;
        s[6 + c] = x * y;
    }
}

/* stack[p, map * 3 + c] for the target's two SSIM maps (y m, (y m)^2): per frame, not per step. */
__kernel void ssim_target_stack(__global const float *gt,     /* [npix, 3] */
                                __global const float *mask,   /* [npix] */
                                const int npix,
                                __global float *stack) {      /* [npix, NTMAP] */
    const int p = get_global_id(0);
    if (p >= npix) return;
    const float m = mask[p];
    __global float *s = stack + (size_t)p * NTMAP;
#pragma unroll
    for (int c = 0; c < 3; c++) {
        const float y = gt[p * 3 + c] * m;
        s[c] = y;
        s[3 + c] = y * y;
    }
}

/* |d| as a bit operation (fabs is an out-of-line call on PoCL, which keeps the work-item loop
 * of the kernel from being vectorised); the same value as fabs. */
inline float abs_bits(float d) {
    return as_float(as_uint(d) & 0x7fffffffu);
}

inline float sign_of(float d) {
    return d > 0.0f ? 1.0f : (d < 0.0f ? -1.0f : 0.0f);   /* 0 at 0, as torch's abs gradient */
}

/* Per pixel: the loss terms (summed per work-group into partial[group, NSUM]) and the gradients:
 * v_feat [npix, CF] of the L1, depth and flow terms (colour: SSIM added by ssim_grad_combine),
 * g_ssim [npix, NGRAD] = dL/d(blurred mu_x, E[xx], E[xy]) per colour.
 * w_l1 = lambda_rgb (1 - lambda_dssim) / n_rgb, w_ssim = lambda_rgb lambda_dssim / n_rgb
 * (n_rgb = 3 sum(mask), at least 1), w_depth = lambda_depth / sum(depth_w), w_flow likewise;
 * where the supervised pixel count is known only on the device (an in-between target made there,
 * a 0 / 1 mask), has_count = 1 and (w_l1, w_ssim) = rgb_weights[count[0]] instead: the host's
 * table of both weights for every count, rounded from the same float64 values as the arguments.
 * flow_delta: the flow error (px) beyond which its loss is linear (INFINITY: squared throughout);
 * has_depth / has_flow = 0 leave those channels' gradients 0.  Local size: a power of two. */
__kernel void image_loss_terms(__global const float *feat,     /* [npix, CF] */
                               __global const float *gt,       /* [npix, 3] */
                               __global const float *mask,     /* [npix] */
                               __global const float *blurred,  /* [npix, NMAP] */
                               __global const float *tblurred, /* [npix, NTMAP]: the target's, per frame */
                               __global const float *depth_gt, /* [npix] */
                               __global const float *depth_w,  /* [npix] */
                               __global const float *flow_gt,  /* [npix, 2] */
                               __global const float *flow_w,   /* [npix] */
                               const int has_depth, const int has_flow,
                               const float w_l1_arg, const float w_ssim_arg, const float w_depth,
                               const float w_flow, const float flow_delta, const int npix,
                               __global float *v_feat,         /* [npix, CF] */
                               __global float *g_ssim,         /* [npix, NGRAD] */
                               __global float *partial,        /* [groups, NSUM] */
                               __local float *scratch,         /* [NSUM, local size] */
                               const int has_count,
                               __global const int *count,      /* [1]: supervised pixels (has_count) */
                               __global const float2 *rgb_weights) { /* [npix + 1]: (w_l1, w_ssim) */
    const float2 w_rgb = has_count ? rgb_weights[clamp(count[0], 0, npix)] : (float2)(w_l1_arg, w_ssim_arg);
    const float w_l1 = w_rgb.x, w_ssim = w_rgb.y;
    const int p = get_global_id(0);
    const int lid = get_local_id(0), lsize = get_local_size(0);
    float sum[NSUM];
    for (int k = 0; k < NSUM; k++) sum[k] = 0.0f;
    if (p < npix) {
        const float m = mask[p];
        __global const float *f = feat + (size_t)p * CF;
        __global const float *b = blurred + (size_t)p * NMAP;
        __global const float *tb = tblurred + (size_t)p * NTMAP;
        __global float *v = v_feat + (size_t)p * CF;
        __global float *g = g_ssim + (size_t)p * NGRAD;
#pragma unroll
        for (int k = 0; k < CF; k++) v[k] = 0.0f;
    #pragma unroll
    for (int c = 0; c < 3; c++) {
            const float d = f[c] - gt[p * 3 + c];
            sum[0] += abs_bits(d) * m;
            sum[4] += d * d * m;
            v[c] = w_l1 * sign_of(d) * m;
            const float mx = b[c], my = tb[c], exx = b[3 + c], eyy = tb[3 + c], exy = b[6 + c];
            const float sxx = exx - mx * mx, syy = eyy - my * my, sxy = exy - mx * my;
            const float A1 = 2.0f * mx * my + SSIM_C1, A2 = 2.0f * sxy + SSIM_C2;
            const float B1 = mx * mx + my * my + SSIM_C1, B2 = sxx + syy + SSIM_C2;
            const float inv_den = 1.0f / (B1 * B2);
            const float S = A1 * A2 * inv_den;
            sum[1] += S * m;
            const float gS = -w_ssim * m;              /* dL/dS: L has -lambda_dssim mean(S) */
            g[c] = gS * (2.0f * my * (A2 - A1) * inv_den - 2.0f * mx * S * (B2 - B1) * inv_den);
            g[3 + c] = gS * (-S / B2);
            g[6 + c] = gS * (2.0f * A1 * inv_den);
        }
        if (has_depth) {
            const float w = depth_w[p];
            const float d = f[CH_DEPTH] - depth_gt[p];
            sum[2] += abs_bits(d) * w;
            v[CH_DEPTH] = w_depth * sign_of(d) * w;
        }
        if (has_flow) {   /* |e|^2, continued as 2 delta |e| - delta^2 beyond |e| = delta (Huber) */
            const float w = flow_w[p];
            const float e0 = f[CH_FLOW] - flow_gt[p * 2], e1 = f[CH_FLOW + 1] - flow_gt[p * 2 + 1];
            const float n2 = e0 * e0 + e1 * e1;
            float scale = 2.0f;                          /* d loss / d e = scale * e */
            if (n2 <= flow_delta * flow_delta) {
                sum[3] += n2 * w;
            } else {
                const float n = sqrt1(n2);
                sum[3] += (2.0f * flow_delta * n - flow_delta * flow_delta) * w;
                scale = 2.0f * flow_delta / n;
            }
            v[CH_FLOW] = w_flow * scale * e0 * w;
            v[CH_FLOW + 1] = w_flow * scale * e1 * w;
        }
    }
    for (int k = 0; k < NSUM; k++) scratch[k * lsize + lid] = sum[k];
    barrier(CLK_LOCAL_MEM_FENCE);
#if defined(DEVICE_SIMT_WIDTH) && DEVICE_SIMT_WIDTH > 1
    /* the pairwise tree over the work-items, a barrier per level */
    for (int s = lsize / 2; s > 0; s >>= 1) {
        if (lid < s)
            for (int k = 0; k < NSUM; k++) scratch[k * lsize + lid] += scratch[k * lsize + lid + s];
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    if (lid < NSUM) partial[get_group_id(0) * NSUM + lid] = scratch[lid * lsize];
#else
    /* Work-item k < NSUM sums term k's column with the same pairwise tree (halves added element
     * by element, s = lsize / 2 .. 1): the same additions in the same order, so the same sums, as
     * the tree over all work-items above, whose barriers cost more on a CPU driver (a pass of
     * PoCL's work-item loop each) than the lsize - 1 additions done by one work-item. */
    if (lid < NSUM) {
        __local float *col = scratch + lid * lsize;
        for (int s = lsize / 2; s > 0; s >>= 1)
            for (int i = 0; i < s; i++) col[i] += col[i + s];
        partial[get_group_id(0) * NSUM + lid] = col[0];
    }
#endif
}

/* v_feat[p, c] += m (gb_mu + 2 x m gb_xx + y m gb_xy) for the colours: the SSIM gradient through
 * the maps of ssim_stack; gb = the blur adjoint of g_ssim.  With use_wavelet, then
 * v_feat[p, c] += w_wavelet * (v_rgb[p, c] (x m when has_mask)): the wavelet term's gradient
 * (v_rgb: the adjoint transform of its cotangents, not yet masked), in the same pass. */
__kernel void ssim_grad_combine(__global const float *feat,   /* [npix, CF] */
                                __global const float *gt,     /* [npix, 3] */
                                __global const float *mask,   /* [npix] */
                                __global const float *gb,     /* [npix, NGRAD] */
                                const int npix,
                                __global float *v_feat,       /* [npix, CF] */
                                const int use_wavelet, const int has_mask, const float w_wavelet,
                                __global const float *v_rgb) { /* [npix, 3] */
    const int p = get_global_id(0);
    if (p >= npix) return;
    const float m = mask[p];
    const float mw = has_mask ? m : 1.0f;   /* the wavelet gradient's mask factor (x 1 is exact) */
#pragma unroll
    for (int c = 0; c < 3; c++) {
        const float x = feat[(size_t)p * CF + c] * m, y = gt[p * 3 + c] * m;
        const __global float *q = gb + (size_t)p * NGRAD;
        float v = v_feat[(size_t)p * CF + c] + m * (q[c] + 2.0f * x * q[3 + c] + y * q[6 + c]);
        if (use_wavelet) v += w_wavelet * (v_rgb[p * 3 + c] * mw);
        v_feat[(size_t)p * CF + c] = v;
    }
}

/* d[p, c] = (feat[p, c] - gt[p, c]) (x mask[p] when has_mask) for c < 3: the masked colour
 * difference the wavelet loss transforms (wavelet.cl masked_diff of the colour channels). */
__kernel void rgb_masked_diff(__global const float *feat, __global const float *gt,
                              __global const float *mask, const int has_mask, const int npix,
                              __global float *d) {
    const int p = get_global_id(0);
    if (p >= npix) return;
#pragma unroll
    for (int c = 0; c < 3; c++) {
        float v = feat[(size_t)p * CF + c] - gt[p * 3 + c];
        if (has_mask) v *= mask[p];
        d[p * 3 + c] = v;
    }
}
