/* The work layout and staging of the vector rasterizer kernels, rasterize_vec.cl and
 * rasterize_vec_bwd.cl (docs/ARCHITECTURE.md "rasterize"): a work-item's block of VW pixels in the
 * lanes of floatVW, the per-Gaussian record rasterize_vec_prep writes, its staging into local
 * memory and the test of the staged cull boxes against a block.  OpenCL C 1.2.
 * Build options: -DVW=<2|4|8|16>, -DBW (block width, divides VW), and blend.h's. */
#ifndef ENDOWAVE_RASTER_VEC_H
#define ENDOWAVE_RASTER_VEC_H
#ifndef VW
#error "raster_vec.h needs -DVW"
#endif
#include "blend.h"   /* vexp.h, raster_common.h, the blend step, skip_threshold, cull_box */

/* A work-item's VW pixels form a BW x BH block (lane l: pixel (l % BW, l / BW) of the block). */
#ifndef BW
#define BW VW
#endif
#define BH (VW / BW)
#if (TILE % BW) != 0 || (VW % BW) != 0 || (TILE % BH) != 0
#error "BW must divide VW and TILE, VW / BW must divide TILE"
#endif
#define BX (TILE / BW)                /* work-items per row of blocks */
#define BY (TILE / BH)                /* rows of blocks */
#define N_WI (BX * BY)                /* work-items per group */

/* Lane geometry: pixel offsets of the lanes inside the block. */
inline intV lane_dx(void) {
    int v[VW];
    for (int l = 0; l < VW; l++) v[l] = l % BW;
    return vloadI(0, v);
}
inline intV lane_dy(void) {
    int v[VW];
    for (int l = 0; l < VW; l++) v[l] = l / BW;
    return vloadI(0, v);
}

/* Per-Gaussian record, written once per call by rasterize_vec_prep (one Gaussian per work-item)
 * and gathered per tile entry by the rasterize_vec kernels: one contiguous read instead of four
 * scattered arrays, and the skip threshold (a bound of a log) and cull box (two sqrt) computed once
 * per Gaussian instead of once per tile entry.  REC4 float4 per Gaussian:
 *   [0] (a, b, c, opac)   [1] cull box (xmin, xmax, ymin, ymax)   [2] (mean x, mean y, thr, 0)
 *   [3 ..] features[0 .. C-1], zero-padded to a multiple of 4. */
#define REC4 (3 + (C + 3) / 4)

/* Gaussian g's record as entry j of a batch of nb staged in local memory, the cull box by
 * coordinate (l_box [4, nb]: xmin, xmax, ymin, ymax) so that box_hits8 tests 8 entries at once. */
inline void stage_gaussian(__global const float4 *rec, int g, int j, int nb, __local float2 *l_mean,
                           __local float4 *l_cop, __local float *l_feat, __local float *l_thr,
                           __local float *l_box) {
    __global const float4 *r = rec + g * REC4;
    l_cop[j] = r[0];
    const float4 bb = r[1];
    l_box[j] = bb.x; l_box[nb + j] = bb.y; l_box[2 * nb + j] = bb.z; l_box[3 * nb + j] = bb.w;
    const float4 m = r[2];
    l_mean[j] = m.xy;
    l_thr[j] = m.z;
    __global const float *f = (__global const float *)(r + 3);
    for (int c = 0; c < C; c++) l_feat[j * C + c] = f[c];
}

/* Gaussian g's record (its first and last cache line) asked for into L1 / into L2 only; no-ops
 * where the build has no prefetch (the callers leave out the address loads there: HAVE_PREFETCH) */
inline void prefetch_record(__global const float4 *rec, int g) {
    PREFETCH(rec + g * REC4);
    PREFETCH(rec + g * REC4 + REC4 - 1);
}
inline void prefetch_record_l2(__global const float4 *rec, int g) {
    PREFETCH_L2(rec + g * REC4);
    PREFETCH_L2(rec + g * REC4 + REC4 - 1);
}

/* entry j of l_box [4, nb]: a box that reaches no block (entries past a batch's end, up to a
 * multiple of 8, which box_hits8 reads) */
inline void stage_no_box(int j, int nb, __local float *l_box) {
    l_box[j] = MAXFLOAT; l_box[nb + j] = -MAXFLOAT; l_box[2 * nb + j] = MAXFLOAT; l_box[3 * nb + j] = -MAXFLOAT;
}

/* 8 consecutive floats of local memory (element loads, merged into one vector load; PoCL calls
 * vload8 out of line) */
inline float8 lload8(__local const float *p) {
    return (float8)(p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7]);
}

/* bit l set where lane l of the mask t (-1 / 0 per lane) is set */
inline uint mask_bits8(int8 t) {
    const int8 b = t & (int8)(1, 2, 4, 8, 16, 32, 64, 128);
    const int4 c = b.lo | b.hi;
    const int2 d = c.lo | c.hi;
    return (uint)(d.x | d.y);
}

/* bit i set where the cull box of entry j0 + i of l_box [4, nb] reaches the pixel centres
 * [px0, px1] x [py0, py1] (i < 8) */
inline uint box_hits8(__local const float *l_box, int nb, int j0, float px0, float px1, float py0, float py1) {
    return mask_bits8((lload8(l_box + j0) <= px1) & (lload8(l_box + nb + j0) >= px0) &
                      (lload8(l_box + 2 * nb + j0) <= py1) & (lload8(l_box + 3 * nb + j0) >= py0));
}

#endif
