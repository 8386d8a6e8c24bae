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

/* Pixels per work-item of image_loss_terms: LOSS_VW = 8 on CPU drivers (one pixel per lane of
 * float8 vectors: PoCL leaves the one-pixel kernel's work-item loop scalar, divisions included),
 * 1 elsewhere.  The per-pixel maths (loss_pixel) is written once over lf = float or float8; lane for
 * lane it is the same operations in the same order, so both builds give the same bits. */
#ifndef LOSS_VW
#define LOSS_VW 1
#endif
#if LOSS_VW == 8
typedef float8 lf;
typedef int8 lmask;
#define LABS(d) as_float8(as_uint8(d) & 0x7fffffffu)   /* fabs without a call (PoCL calls it) */
#define LSQRT(x) sqrt8(x)
/* lane l of element k of rows of `stride` floats: pixel q[l] (loads), p0 + l (stores) */
FORCE_INLINE lf ld_lanes(__global const float *a, const int *q, const int stride, const int k) {
    return (lf)(a[q[0] * stride + k], a[q[1] * stride + k], a[q[2] * stride + k], a[q[3] * stride + k],
                a[q[4] * stride + k], a[q[5] * stride + k], a[q[6] * stride + k], a[q[7] * stride + k]);
}
/* out[k] = ld_lanes(a, q, stride, k) for k < stride where the 8 pixels are p0 .. p0 + 7 (their
 * rows one run of 8 stride floats: constant offsets once inlined) */
FORCE_INLINE void ld_block(__global const float *a, const int p0, const int stride, lf *out) {
    __global const float *r = a + p0 * stride;
    for (int k = 0; k < stride; k++)
        out[k] = (lf)(r[k], r[stride + k], r[2 * stride + k], r[3 * stride + k], r[4 * stride + k],
                      r[5 * stride + k], r[6 * stride + k], r[7 * stride + k]);
}
/* the inverse of ld_block: v[0 .. stride - 1] to the rows of pixels p0 .. p0 + 7 */
FORCE_INLINE void st_block(__global float *a, const int p0, const int stride, const lf *v) {
    __global float *r = a + p0 * stride;
    for (int k = 0; k < stride; k++) {
        r[k] = v[k].s0; r[stride + k] = v[k].s1; r[2 * stride + k] = v[k].s2; r[3 * stride + k] = v[k].s3;
        r[4 * stride + k] = v[k].s4; r[5 * stride + k] = v[k].s5; r[6 * stride + k] = v[k].s6;
        r[7 * stride + k] = v[k].s7;
    }
}
FORCE_INLINE void st_lanes(__global float *a, const int p0, const int npix, const int stride, const int k, const lf v) {
    const float x[8] = {v.s0, v.s1, v.s2, v.s3, v.s4, v.s5, v.s6, v.s7};
    for (int l = 0; l < 8; l++)
        if (p0 + l < npix) a[(p0 + l) * stride + k] = x[l];
}
#elif LOSS_VW == 1
typedef float lf;
typedef int lmask;
#define LABS(d) as_float(as_uint(d) & 0x7fffffffu)
#define LSQRT(x) sqrt1(x)
FORCE_INLINE lf ld_lanes(__global const float *a, const int *q, const int stride, const int k) {
    return a[q[0] * stride + k];
}
FORCE_INLINE void st_lanes(__global float *a, const int p0, const int npix, const int stride, const int k, const lf v) {
    a[p0 * stride + k] = v;
}
#else
#error "LOSS_VW must be 1 or 8"
#endif
/* sign(d), 0 at 0 (as torch's abs gradient) */
#define LSIGN(d) ((d) > 0.0f ? (lf)(1.0f) : ((d) < 0.0f ? (lf)(-1.0f) : (lf)(0.0f)))

/* One pixel per lane.  In: f [CF] the rendered channels, y [3] the target colour, m the mask, b
 * [NMAP] the blurred render maps, tb [NTMAP] the target's, the depth target and weight, the flow
 * target and weight.  Out: v [CF] (every channel written), g [NGRAD]; sum [NSUM] is added to. */
FORCE_INLINE void loss_pixel(const lf *f, const lf *y, const lf m, const lf *b, const lf *tb, const lf dgt,
                       const lf dw, const lf fg0, const lf fg1, const lf fw, const int has_depth,
                       const int has_flow, const float w_l1, const float w_ssim, const float w_depth,
                       const float w_flow, const float flow_delta, lf *v, lf *g, lf *sum) {
    for (int k = 0; k < CF; k++) v[k] = (lf)(0.0f);
#pragma unroll
    for (int c = 0; c < 3; c++) {
        const lf d = f[c] - y[c];
        sum[0] += LABS(d) * m;
        sum[4] += d * d * m;
        v[c] = w_l1 * LSIGN(d) * m;
        const lf mx = b[c], my = tb[c], exx = b[3 + c], eyy = tb[3 + c], exy = b[6 + c];
        const lf sxx = exx - mx * mx, syy = eyy - my * my, sxy = exy - mx * my;
        const lf A1 = 2.0f * mx * my + SSIM_C1, A2 = 2.0f * sxy + SSIM_C2;
        const lf B1 = mx * mx + my * my + SSIM_C1, B2 = sxx + syy + SSIM_C2;
        const lf inv_den = 1.0f / (B1 * B2);
        const lf S = A1 * A2 * inv_den;
        sum[1] += S * m;
        const lf gS = -w_ssim * m;              /* dL/dS: L has -lambda_dssim mean(S) */
        g[c] = gS * (2.0f * my * (A2 - A1) * inv_den - 2.0f * mx * S * (B2 - B1) * inv_den);
        g[3 + c] = gS * (-S / B2);
        g[6 + c] = gS * (2.0f * A1 * inv_den);
    }
    if (has_depth) {
        const lf d = f[CH_DEPTH] - dgt;
        sum[2] += LABS(d) * dw;
        v[CH_DEPTH] = w_depth * LSIGN(d) * dw;
    }
    if (has_flow) {   /* |e|^2, continued as 2 delta |e| - delta^2 beyond |e| = delta (Huber) */
        const lf e0 = f[CH_FLOW] - fg0, e1 = f[CH_FLOW + 1] - fg1;
        const lf n2 = e0 * e0 + e1 * e1;
        /* both sides for every lane, the pixel's chosen by its n2 (the other may be inf or NaN) */
        const lf n = LSQRT(n2);
        const lmask quad = n2 <= flow_delta * flow_delta;
        sum[3] += (quad ? n2 : 2.0f * flow_delta * n - flow_delta * flow_delta) * fw;
        const lf scale = quad ? (lf)(2.0f) : 2.0f * flow_delta / n;   /* d loss / d e = scale * e */
        v[CH_FLOW] = w_flow * scale * e0 * fw;
        v[CH_FLOW + 1] = w_flow * scale * e1 * fw;
    }
}

/* Per pixel: the loss terms (summed per work-group into partial[group, NSUM]) and the gradients:
 * v_feat [npix, CF] of the L1, depth and flow terms (colour: SSIM added by ssim_grad_combine),
 * g_ssim [npix, NGRAD] = dL/d(blurred mu_x, E[xx], E[xy]) per colour.
 * w_l1 = lambda_rgb (1 - lambda_dssim) / n_rgb, w_ssim = lambda_rgb lambda_dssim / n_rgb
 * (n_rgb = 3 sum(mask), at least 1), w_depth = lambda_depth / sum(depth_w), w_flow likewise;
 * flow_delta: the flow error (px) beyond which its loss is linear (INFINITY: squared throughout);
 * has_depth / has_flow = 0 leave those channels' gradients 0.  Work-item i takes pixels
 * LOSS_VW i .. LOSS_VW i + LOSS_VW - 1; a work-group's pixels (LOSS_VW x its size, a power of two)
 * are summed by the same pairwise tree whatever LOSS_VW is. */
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
                               const float w_l1, const float w_ssim, const float w_depth,
                               const float w_flow, const float flow_delta, const int npix,
                               __global float *v_feat,         /* [npix, CF] */
                               __global float *g_ssim,         /* [npix, NGRAD] */
                               __global float *partial,        /* [groups, NSUM] */
                               __local float *scratch) {       /* [NSUM, pixels per group] */
    const int lid = get_local_id(0), lsize = get_local_size(0) * LOSS_VW;   /* lsize: pixels per group */
    const int p0 = get_global_id(0) * LOSS_VW;                              /* lane 0's pixel */
    lf sum[NSUM];
    for (int k = 0; k < NSUM; k++) sum[k] = (lf)(0.0f);
    if (p0 < npix) {
        int q[LOSS_VW];   /* lane l reads pixel p0 + l; the lanes past the last pixel read the last
                           * one, and their results are dropped */
        for (int l = 0; l < LOSS_VW; l++) q[l] = p0 + l < npix ? p0 + l : npix - 1;
        lf f[CF], y[3], b[NMAP], tb[NTMAP], v[CF], g[NGRAD];
        lf dgt = (lf)(0.0f), dw = (lf)(0.0f), fg0 = (lf)(0.0f), fg1 = (lf)(0.0f), fw = (lf)(0.0f);
#if LOSS_VW == 8
        if (p0 + 8 <= npix) {
            ld_block(feat, p0, CF, f);
            ld_block(gt, p0, 3, y);
            ld_block(blurred, p0, NMAP, b);
            ld_block(tblurred, p0, NTMAP, tb);
        } else
#endif
        {
            for (int k = 0; k < CF; k++) f[k] = ld_lanes(feat, q, CF, k);
            for (int c = 0; c < 3; c++) y[c] = ld_lanes(gt, q, 3, c);
            for (int k = 0; k < NMAP; k++) b[k] = ld_lanes(blurred, q, NMAP, k);
            for (int k = 0; k < NTMAP; k++) tb[k] = ld_lanes(tblurred, q, NTMAP, k);
        }
        const lf m = ld_lanes(mask, q, 1, 0);
        if (has_depth) {
            dgt = ld_lanes(depth_gt, q, 1, 0);
            dw = ld_lanes(depth_w, q, 1, 0);
        }
        if (has_flow) {
            fg0 = ld_lanes(flow_gt, q, 2, 0);
            fg1 = ld_lanes(flow_gt, q, 2, 1);
            fw = ld_lanes(flow_w, q, 1, 0);
        }
        loss_pixel(f, y, m, b, tb, dgt, dw, fg0, fg1, fw, has_depth, has_flow, w_l1, w_ssim, w_depth, w_flow,
                   flow_delta, v, g, sum);
#if LOSS_VW == 8
        if (p0 + 8 <= npix) {
            st_block(v_feat, p0, CF, v);
            st_block(g_ssim, p0, NGRAD, g);
        } else
#endif
        {
            for (int k = 0; k < CF; k++) st_lanes(v_feat, p0, npix, CF, k, v[k]);
            for (int k = 0; k < NGRAD; k++) st_lanes(g_ssim, p0, npix, NGRAD, k, g[k]);
        }
    }
    /* scratch[k, pixel]: the pixel's term k (0 for the pixels past the image) */
    for (int k = 0; k < NSUM; k++) {
#if LOSS_VW == 1
        scratch[k * lsize + lid] = sum[k];
#else
        const lf t = sum[k];
        const float x[8] = {t.s0, t.s1, t.s2, t.s3, t.s4, t.s5, t.s6, t.s7};
        for (int l = 0; l < LOSS_VW; l++) scratch[k * lsize + lid * LOSS_VW + l] = p0 + l < npix ? x[l] : 0.0f;
#endif
    }
    barrier(CLK_LOCAL_MEM_FENCE);
#if defined(DEVICE_SIMT_WIDTH) && DEVICE_SIMT_WIDTH > 1 && LOSS_VW == 1
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
