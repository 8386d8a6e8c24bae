/* The blend rule of the four rasterizer kernels, written once (docs/ARCHITECTURE.md "rasterize").
 * OpenCL C 1.2.  Included by rasterize.cl, rasterize_bwd.cl (one pixel per work-item, the GPU
 * path) and rasterize_vec.cl, rasterize_vec_bwd.cl (VW pixels per work-item in floatVW lanes, the
 * CPU path; they define VW and include raster_vec.h).
 *
 *   per Gaussian   skip_threshold (the power below which it is skipped without exp), cull_box (the
 *                  pixel box where it can pass that test) and ln_upper behind them
 *   per sub-block  SUB x SUB pixel blocks of a tile: build_sub_lists (the scalar forward) and
 *                  sub_block_mask (the scalar adjoint) from the cull boxes
 *   per pixel      the blend step of one Gaussian at one pixel (float) or at VW pixels (floatVW,
 *                  suffix _v), forward and adjoint: blend_power, blend_alpha, blend_open,
 *                  blend_behind, blend_inv_om, blend_power_grad.  One definition for both types
 *                  (BLEND_STEPS), so the scalar and vector kernels make the same skips and compute
 *                  the same values lane for lane.
 *
 * The rule (per pixel, front to back; docs/ARCHITECTURE.md): power = -1/2 d^T A d with d = mean -
 * pixel centre and A the conic; a Gaussian is skipped where power > 0 or power < its skip
 * threshold; alpha = min(ALPHA_MAX, opac exp(power)), skipped below ALPHA_MIN; the pixel stops
 * before a Gaussian that would bring T (1 - alpha) below T_STOP; else it adds features alpha T and
 * T becomes T (1 - alpha).  The adjoint walks back to front and recovers T by division.
 *
 * What the kernels still write each in their own way: the loop and its lane masks, and the
 * adjoint's d L / d alpha.  The scalar adjoint keeps the colour behind per channel (S_c) and forms
 * v_alpha T_final / (1 - alpha) + sum_c vo_c (f_c T - S_c / (1 - alpha)); the vector adjoint keeps
 * only D = sum_c vo_c S_c and forms (v_alpha T_final - D) / (1 - alpha) + T sum_c vo_c f_c.  Equal
 * in exact arithmetic, not in float rounding, so each stays where it is (moving either would
 * change the variant's bits).
 *
 * Build options: -DC, -DALPHA_MAX, -DALPHA_MIN, -DT_STOP (endowave_cl/ops/raster_options.py), and
 * -DVW for the vector kernels.
 */
#ifndef ENDOWAVE_BLEND_H
#define ENDOWAVE_BLEND_H
#include "raster_common.h"   /* common.h, exp_nonpos, TileWork, the shared arguments */
#ifdef VW
#include "vexp.h"            /* floatV, intV, vexp_nonpos */
#endif

/* ------------------------------------------------------------------ skip and cull, per Gaussian */

/* An upper bound of ln(x) for a normal x > 0 without a call (PoCL calls log out of line):
 * x = 2^e m, m in [1, 2), and log2(m) <= p(m - 1.5) + LOG2_POLY_UP, with p the cubic least-squares
 * fit to log2 on [1, 2] below, lifted by its largest shortfall there (5.4e-4, float32 evaluation
 * included) and 2e-4 more: at most 2.1e-3 above log2(m), 1.5e-3 above ln(x).  (project4d's
 * p4_log_upper, the tangent alone, is up to 0.09 above: enough for its tile rect.) */
#define LOG2_POLY_UP 7.4e-4f
inline float ln_upper(float x) {
    const int bits = as_int(x);
    const float e = as_float((bits >> 23) | 0x4B000000) - (8388608.0f + 127.0f);   /* exponent, exact */
    const float t = as_float((bits & 0x007fffff) | 0x3f800000) - 1.5f;             /* m - 1.5, exact */
    const float p = ((0.15391242f * t - 0.33688030f) * t + 0.96116853f) * t + 0.58537829f;
    return 0.693147181f * (e + (p + LOG2_POLY_UP));
}

/* Early skip without exp: alpha = min(ALPHA_MAX, opac exp(power)) < ALPHA_MIN whenever
 * power < log(ALPHA_MIN / opac) - SKIP_MARGIN.  SKIP_MARGIN (in log units, i.e. a 0.1% factor on
 * alpha) is far above the rounding of exp, so the skip never drops a Gaussian the exact test
 * keeps.  The log is taken from below, -ln_upper(opac / ALPHA_MIN) (at most 1.5e-3 lower): a lower
 * threshold only sends a few more pairs to the exact test, which skips them, so the results are
 * those of the exact log.  opac < ALPHA_MIN can never contribute: threshold +inf. */
#define SKIP_MARGIN 1e-3f
inline float skip_threshold(float opacity) {
    return opacity >= ALPHA_MIN ? -ln_upper(opacity / ALPHA_MIN) - SKIP_MARGIN : INFINITY;
}

/* Culling.  The box bounds the ellipse power >= skip threshold, i.e. d^T A d <= q with q = -2 thr:
 * |dx| <= sqrt(q (A^-1)_xx) = sqrt(q c / det), |dy| <= sqrt(q a / det); widened by BOX_SLACK
 * (relative) and BOX_PAD (pixels) against rounding.  Outside it every pixel would skip the
 * Gaussian anyway, so culling by it gives the results of walking the whole tile list.  A conic
 * that is not positive definite gets an infinite box (no culling). */
#define BOX_SLACK 1.001f
#define BOX_PAD 0.01f
inline float4 cull_box(float2 mean, float4 cop, float thr) {   /* (xmin, xmax, ymin, ymax) */
    if (!(thr < 0.0f)) return (float4)(INFINITY, -INFINITY, INFINITY, -INFINITY);   /* never */
    const float det = cop.x * cop.z - cop.y * cop.y;
    if (!(det > 0.0f && cop.x > 0.0f && cop.z > 0.0f))
        return (float4)(-INFINITY, INFINITY, -INFINITY, INFINITY);                  /* always */
    const float q = -2.0f * thr;
    const float ex = sqrt1(q * cop.z / det) * BOX_SLACK + BOX_PAD;   /* sqrt1: common.h */
    const float ey = sqrt1(q * cop.x / det) * BOX_SLACK + BOX_PAD;
    return (float4)(mean.x - ex, mean.x + ex, mean.y - ey, mean.y + ey);
}

/* ------------------------------------------------------- cull boxes against the tile's sub-blocks */

/* The scalar kernels split the tile into SUB x SUB pixel blocks and test each Gaussian's cull box
 * against a block's pixel centres (the vector kernels test against their work-item's own block,
 * box_hits8 in raster_vec.h). */
#define SUB 4
#define SUBS_PER_ROW (TILE / SUB)
#define N_SUB (SUBS_PER_ROW * SUBS_PER_ROW)

/* Forward: work-item blk < N_SUB fills the list of sub-block blk (tile origin x0, y0 in pixels)
 * with the indices j < count (<= 256, so they fit a uchar) whose box holds one of the block's pixel
 * centres, in increasing j.  List blk starts at l_list + blk * stride. */
inline void build_sub_lists(int blk, int count, int x0, int y0, __local const float4 *l_box,
                            __local uchar *l_list, __local int *l_len, int stride) {
    if (blk >= N_SUB) return;
    const float bx0 = (float)(x0 + (blk % SUBS_PER_ROW) * SUB) + 0.5f, bx1 = bx0 + (float)(SUB - 1);
    const float by0 = (float)(y0 + (blk / SUBS_PER_ROW) * SUB) + 0.5f, by1 = by0 + (float)(SUB - 1);
    __local uchar *list = l_list + blk * stride;
    int n = 0;
    for (int j = 0; j < count; j++) {
        const float4 bb = l_box[j];
        if (bb.x <= bx1 && bb.y >= bx0 && bb.z <= by1 && bb.w >= by0) list[n++] = (uchar)j;
    }
    l_len[blk] = n;
}

/* Adjoint: bit s set when the cull box (xmin, xmax, ymin, ymax) reaches a pixel centre of
 * sub-block s of the tile with pixel origin (x0, y0). */
inline int sub_block_mask(float4 bb, int x0, int y0) {
    int cols = 0, rows = 0;
    for (int s = 0; s < SUBS_PER_ROW; s++) {
        const float bx0 = (float)(x0 + s * SUB) + 0.5f, bx1 = bx0 + (float)(SUB - 1);
        const float by0 = (float)(y0 + s * SUB) + 0.5f, by1 = by0 + (float)(SUB - 1);
        if (bb.x <= bx1 && bb.y >= bx0) cols |= 1 << s;
        if (bb.z <= by1 && bb.w >= by0) rows |= 1 << s;
    }
    int mask = 0;
    for (int r = 0; r < SUBS_PER_ROW; r++)
        if (rows & (1 << r)) mask |= cols << (r * SUBS_PER_ROW);
    return mask;
}

/* ------------------------------------------------------------- the blend step, per pixel or lane */

/* BLEND_STEPS(FT, S, EXPF) defines the step functions for pixel values of type FT (float, or
 * floatV for VW pixels) with suffix S, EXPF the matching exp of a power <= 0.  A Gaussian's own
 * values (cop = (a, b, c, opac), the conic and opacity) are float in both.  Each function body is
 * the one expression the kernels used to write out, so the compiler sees the same operations (and
 * makes the same contractions) as before; lane for lane the vector functions give the scalar bits.
 *
 *   blend_power(cop, dx, dy)   power = -1/2 d^T A d at d = (dx, dy) = mean - pixel centre
 *   blend_G(power)             exp(power), power <= 0
 *   blend_alpha(opac, G)       alpha = min(ALPHA_MAX, opac G)
 *   blend_open(opac, G)        opac G <= ALPHA_MAX: the clamp is not active, so alpha passes a
 *                              gradient to opac and power (a lane mask for floatV)
 *   blend_behind(t, alpha)     forward: the transmittance behind the Gaussian, t (1 - alpha); its
 *                              weight is alpha t (t: in front)
 *   blend_inv_om(alpha)        adjoint: 1 / (1 - alpha); T in front = T behind * blend_inv_om,
 *                              the weight alpha T (alpha <= ALPHA_MAX keeps 1 - alpha >= 1 - ALPHA_MAX)
 *   blend_power_grad(v_power, cop, dx, dy, g)
 *                              adjoint: g[0..4] = the gradient to the mean (2) and the conic
 *                              (a, b, c) of v_power = d L / d power = (d L / d alpha) alpha; the
 *                              opacity's is (d L / d alpha) G, the features' vo_c alpha T. */
#define BLEND_STEPS(FT, S, EXPF)                                                           \
inline FT blend_power##S(float4 cop, FT dx, FT dy) {                                     \
    return -0.5f * (cop.x * dx * dx + cop.z * dy * dy) - cop.y * dx * dy;                \
}                                                                                          \
inline FT blend_G##S(FT power) { return EXPF(power); }                                   \
inline FT blend_alpha##S(float opac, FT G) {                                             \
    const FT raw = opac * G;                                                               \
    return raw < ALPHA_MAX ? raw : (FT)(ALPHA_MAX);                                        \
}                                                                                          \
inline FT blend_behind##S(FT t, FT alpha) { return t * (1.0f - alpha); }                 \
inline FT blend_inv_om##S(FT alpha) { return 1.0f / (1.0f - alpha); }                    \
inline void blend_power_grad##S(FT v_power, float4 cop, FT dx, FT dy, FT *g) {           \
    g[0] = -v_power * (cop.x * dx + cop.y * dy);                                           \
    g[1] = -v_power * (cop.z * dy + cop.y * dx);                                           \
    g[2] = -0.5f * v_power * dx * dx;                                                      \
    g[3] = -v_power * dx * dy;                                                             \
    g[4] = -0.5f * v_power * dy * dy;                                                      \
}

BLEND_STEPS(float, , exp_nonpos)
inline int blend_open(float opac, float G) { return opac * G <= ALPHA_MAX; }
#ifdef VW
BLEND_STEPS(floatV, _v, vexp_nonpos)
inline intV blend_open_v(float opac, floatV G) { return opac * G <= ALPHA_MAX; }
#endif

#endif
