/* Tile rasterizer, forward (docs/ARCHITECTURE.md "rasterize").  OpenCL C 1.2.
 *
 * One work-group of TILE x TILE work-items per screen tile; work-item (lx, ly) owns pixel
 * (tx * TILE + lx, ty * TILE + ly).  The tile's Gaussians (its range of the depth-sorted list) are
 * staged through local memory in batches of TILE_PIXELS (one Gaussian loaded per work-item) and
 * composited front to back.  A pixel stops on its own (T would fall below T_STOP); the group stops
 * loading batches once every pixel has stopped.  Work-items outside the image start "done": they
 * help loading but write nothing.  Every work-item reaches every barrier.
 *
 * Build options (set by endowave_cl/ops/rasterize.py from the constants of
 * endowave_cl/reference/rasterize.py): -DC=<channels>, -DALPHA_MAX, -DALPHA_MIN, -DT_STOP.
 * Pixel centre convention: pixel (i, j) has centre (i + 0.5, j + 0.5).
 */
#include "common.h"

/* Exponent of the 2D Gaussian at offset d = mean - pixel; cop = (a, b, c, opac), the conic
 * (inverse 2D covariance) entries inv00, inv01, inv11. */
inline float gauss_power(float4 cop, float2 d) {
    return -0.5f * (cop.x * d.x * d.x + cop.z * d.y * d.y) - cop.y * d.x * d.y;
}

__kernel __attribute__((reqd_work_group_size(TILE, TILE, 1)))
void rasterize(__global const float2 *means2d,   /* [N, 2] */
               __global const float *conic,      /* [N, 3] (a, b, c) */
               __global const float *opac,       /* [N] */
               __global const float *features,   /* [N, C] */
               __global const int *sorted_values,/* [M] Gaussian ids, tile-major then depth */
               __global const int2 *tile_ranges, /* [n_tiles] (start, end) */
               const int width, const int height, const int tiles_x,
               __global float *out,              /* [H, W, C] */
               __global float *alpha_out,        /* [H, W] */
               __global float *t_final,          /* [H, W] */
               __global int *last_out)           /* [H, W] */
{
    __local float2 l_mean[TILE_PIXELS];
    __local float4 l_cop[TILE_PIXELS];           /* (a, b, c, opac) */
    __local float l_feat[TILE_PIXELS * C];
    __local int l_done[2];                       /* done-pixel counters, used alternately */

    const int lx = get_local_id(0), ly = get_local_id(1);
    const int lid = ly * TILE + lx;
    const int tx = get_group_id(0), ty = get_group_id(1);
    const int tile = ty * tiles_x + tx;
    const int ix = get_global_id(0), iy = get_global_id(1);
    const bool inside = ix < width && iy < height;
    const float px = (float)ix + 0.5f, py = (float)iy + 0.5f;

    const int2 range = tile_ranges[tile];
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
        }
        barrier(CLK_LOCAL_MEM_FENCE);

        for (int j = 0; j < count && !done; j++) {
            const float4 cop = l_cop[j];
            const float2 d = l_mean[j] - (float2)(px, py);
            const float power = gauss_power(cop, d);
            if (power > 0.0f) continue;
            const float alpha = fmin(ALPHA_MAX, cop.w * exp(power));
            if (alpha < ALPHA_MIN) continue;
            const float t_next = T * (1.0f - alpha);
            if (t_next < T_STOP) { done = true; break; }
            const float w = alpha * T;
            for (int c = 0; c < C; c++) acc[c] += l_feat[j * C + c] * w;
            T = t_next;
            last = b * TILE_PIXELS + j + 1;
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
