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
#include "blend.h"   /* the blend step, skip_threshold, cull_box, build_sub_lists; raster_common.h */

__kernel __attribute__((reqd_work_group_size(TILE, TILE, 1)))
void rasterize(__global const float2 *means2d,   /* [N, 2] */
               __global const float *conic,      /* [N, 3] (a, b, c) */
               __global const float *opac,       /* [N] */
               __global const float *features,   /* [N, C] */
               RASTER_LIST_ARGS, RASTER_FWD_OUT_ARGS)
{
    RASTER_BATCH_LOCALS(TILE_PIXELS);
    __local float4 l_box[TILE_PIXELS];           /* cull box (xmin, xmax, ymin, ymax) */
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
                const float power = blend_power(cop, d.x, d.y);   /* blend.h */
                if (power > 0.0f || power < l_thr[j]) continue;
                const float alpha = blend_alpha(cop.w, blend_G(power));
                if (alpha < ALPHA_MIN) continue;
                const float t_next = blend_behind(t_cur, alpha);
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
