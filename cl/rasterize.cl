/* Tile rasterizer, forward (docs/ARCHITECTURE.md "rasterize").  OpenCL C 1.2.
 *
 * One work-group of TILE x TILE work-items per screen tile; work-item (lx, ly) owns pixel
 * (tx * TILE + lx, ty * TILE + ly).  The tile's Gaussians (its range of the depth-sorted list) are
 * staged through local memory in batches of TILE_PIXELS (one Gaussian loaded per work-item) and
 * composited front to back.  A pixel stops on its own (T would fall below T_STOP); the group stops
 * loading batches once every pixel has stopped.  Work-items outside the image start "done": they
 * help loading but write nothing.  Every work-item reaches every barrier.
 *
 * Culling (exact: it drops only pairs the compositing rules would skip): per batch, each 4 x 4
 * sub-block of the tile gets the ordered list of the batch's Gaussians that can reach one of its
 * pixels (cull_box), and a pixel walks only its sub-block's list; within it, a pair whose power
 * is below the Gaussian's skip threshold is dropped before exp.  On PoCL this cuts the pairs
 * walked about 4x against walking the whole tile list.
 *
 * Build options (set by endowave_cl/ops/rasterize.py from the constants of
 * endowave_cl/reference/rasterize.py): -DC=<channels>, -DALPHA_MAX, -DALPHA_MIN, -DT_STOP.
 * Pixel centre convention: pixel (i, j) has centre (i + 0.5, j + 0.5).
 */
#include "raster_common.h"   /* exp_nonpos, TileWork, the shared arguments */

/* The helpers below are shared with rasterize_bwd.cl, which includes this file with
 * RASTERIZE_HELPERS_ONLY defined, so both passes make the same skip decisions. */

/* Exponent of the 2D Gaussian at offset d = mean - pixel; cop = (a, b, c, opac), the conic
 * (inverse 2D covariance) entries inv00, inv01, inv11. */
inline float gauss_power(float4 cop, float2 d) {
    return -0.5f * (cop.x * d.x * d.x + cop.z * d.y * d.y) - cop.y * d.x * d.y;
}

/* exp_nonpos: raster_common.h */

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

/* Sub-block culling.  The tile is split into SUB x SUB pixel blocks; per batch, each block gets the
 * ordered list of the batch's Gaussians whose box can reach one of its pixel centres, and a pixel
 * walks only its block's list.  The box bounds the ellipse power >= skip threshold, i.e.
 * d^T A d <= q with q = -2 thr: |dx| <= sqrt(q (A^-1)_xx) = sqrt(q c / det), |dy| <= sqrt(q a / det);
 * widened by BOX_SLACK (relative) and BOX_PAD (pixels) against rounding.  Outside it every pixel
 * would skip the Gaussian anyway, so the result is the same as walking the whole tile list.
 * A conic that is not positive definite gets an infinite box (no culling). */
#define SUB 4
#define SUBS_PER_ROW (TILE / SUB)
#define N_SUB (SUBS_PER_ROW * SUBS_PER_ROW)
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

/* Work-item blk < N_SUB fills the list of sub-block blk (tile origin x0, y0 in pixels) with the
 * indices j < count (<= 256, so they fit a uchar) whose box holds one of the block's pixel
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

#ifndef RASTERIZE_HELPERS_ONLY
__kernel __attribute__((reqd_work_group_size(TILE, TILE, 1)))
void rasterize(__global const float2 *means2d,   /* [N, 2] */
               __global const float *conic,      /* [N, 3] (a, b, c) */
               __global const float *opac,       /* [N] */
               __global const float *features,   /* [N, C] */
               RASTER_LIST_ARGS, RASTER_FWD_OUT_ARGS)
{
    RASTER_BATCH_LOCALS(TILE_PIXELS);
    __local uchar l_list[N_SUB * TILE_PIXELS];   /* per sub-block lists of batch indices */
    __local int l_len[N_SUB];
    __local int l_done[2];                       /* done-pixel counters, used alternately */

    const TileWork w = tile_work(1, 1, tiles_x);
    const int lid = w.lid, tx = w.tx, ty = w.ty;
    const int ix = w.x0, iy = w.y0;
    const bool inside = ix < width && iy < height;
    const float px = w.px0, py = w.py0;
    const int my_sub = (w.ly / SUB) * SUBS_PER_ROW + w.lx / SUB;

    const int2 range = tile_ranges[w.tile];
    const int n_entries = range.y - range.x;
    const int n_batches = (n_entries + TILE_PIXELS - 1) / TILE_PIXELS;

    float T = 1.0f;
    float acc[C];
    for (int c = 0; c < C; c++) acc[c] = 0.0f;
    int last = 0;
    bool done = !inside;

    if (lid < 2) l_done[lid] = 0;
    barrier(CLK_LOCAL_MEM_FENCE);

    for (int b = 0; b < n_batches; b++) {
        /* Count finished pixels; the count is uniform after the barrier, so is the break. */
        if (lid == 0) l_done[(b + 1) & 1] = 0;
        if (done) atomic_inc(&l_done[b & 1]);
        barrier(CLK_LOCAL_MEM_FENCE);
        if (l_done[b & 1] == TILE_PIXELS) break;

        const int base = range.x + b * TILE_PIXELS;
        const int count = min(TILE_PIXELS, range.y - base);
        if (lid < count) {
            const int g = sorted_values[base + lid];
            l_mean[lid] = means2d[g];
            l_cop[lid] = (float4)(conic[3 * g], conic[3 * g + 1], conic[3 * g + 2], opac[g]);
            for (int c = 0; c < C; c++) l_feat[lid * C + c] = features[g * C + c];
            const float thr = skip_threshold(l_cop[lid].w);
            l_thr[lid] = thr;
            l_box[lid] = cull_box(l_mean[lid], l_cop[lid], thr);
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        build_sub_lists(lid, count, tx * TILE, ty * TILE, l_box, l_list, l_len, TILE_PIXELS);
        barrier(CLK_LOCAL_MEM_FENCE);

        const int n_mine = l_len[my_sub];
        __local const uchar *mine = l_list + my_sub * TILE_PIXELS;
        if (!done) {
            /* work on copies: the originals live across barriers (PoCL keeps them in memory) */
            float t_cur = T;
            float a_cur[C];
            for (int c = 0; c < C; c++) a_cur[c] = acc[c];
            int last_cur = last;
            bool stop = false;
            for (int i = 0; i < n_mine; i++) {
                const int j = mine[i];
                const float4 cop = l_cop[j];
                const float2 d = l_mean[j] - (float2)(px, py);
                const float power = gauss_power(cop, d);
                if (power > 0.0f || power < l_thr[j]) continue;
                const float raw = cop.w * exp_nonpos(power);
                const float alpha = raw < ALPHA_MAX ? raw : ALPHA_MAX;
                if (alpha < ALPHA_MIN) continue;
                const float t_next = t_cur * (1.0f - alpha);
                if (t_next < T_STOP) { stop = true; break; }
                const float w = alpha * t_cur;
                for (int c = 0; c < C; c++) a_cur[c] += l_feat[j * C + c] * w;
                t_cur = t_next;
                last_cur = b * TILE_PIXELS + j + 1;
            }
            T = t_cur;
            for (int c = 0; c < C; c++) acc[c] = a_cur[c];
            last = last_cur;
            done = stop;
        }
        barrier(CLK_LOCAL_MEM_FENCE);   /* the next batch overwrites the local arrays */
    }

    if (inside) {
        const int p = iy * width + ix;
        for (int c = 0; c < C; c++) out[p * C + c] = acc[c];
        alpha_out[p] = 1.0f - T;
        t_final[p] = T;
        last_out[p] = last;
    }
}
#endif  /* RASTERIZE_HELPERS_ONLY */
