/* Tile rasterizer, forward, explicit-SIMD variant for CPU OpenCL drivers (docs/ARCHITECTURE.md
 * "rasterize").  OpenCL C 1.2.
 *
 * Same results and rules as rasterize.cl (the GPU path, one pixel per work-item), but each
 * work-item composites VW pixels held in the lanes of floatVW vectors: PoCL does not vectorise the
 * per-pixel loop of the scalar kernel, so the SIMD is written out here.  Each
 * work-item owns a block of BW x BH = VW pixels (lane l: pixel (l % BW, l / BW) of the block); a
 * tile is one work-group of BX x BY = (TILE / BW) x (TILE / BH) work-items, work-item (lx, ly) owning
 * the block at pixel (tx * TILE + lx * BW, ty * TILE + ly * BH).
 *
 * The tile's Gaussians are staged through local memory in batches of FWD_BATCH, front to back.  Per
 * lane the compositing is exactly that of rasterize.cl (same helper functions, same operation
 * order; vexp_nonpos equals exp_nonpos bit for bit): skip power > 0, alpha = min(ALPHA_MAX, opac G),
 * skip alpha < ALPHA_MIN, stop before a Gaussian that would bring T below T_STOP.  Lanes are masked
 * (vector ?:): a lane that skips or is done adds nothing; the work-item leaves the batch once all its
 * lanes are done, and the group stops loading batches once every work-item is done.  The walk keeps
 * each adding hit's weights alpha T; the colour is summed from them after the walk, per channel in
 * the hits' order (the same bits as adding it hit by hit).
 *
 * Culling (exact, as in rasterize.cl): per batch, each work-item tests the staged cull boxes against
 * its block 8 at a time (box_hits8) into a bit mask of the batch's entries, then walks the set bits
 * in order and masks lanes whose power is below the skip threshold.  Every work-item reaches every
 * barrier.
 *
 * Build options: -DC, -DALPHA_MAX, -DALPHA_MIN, -DT_STOP (as rasterize.cl), -DVW=<2|4|8|16>,
 * -DBW (block width, divides VW).
 */
#include "common.h"
#include "vexp.h"
#define RASTERIZE_HELPERS_ONLY
#include "rasterize.cl"   /* gauss_power, exp_nonpos, skip_threshold, cull_box */

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

#ifndef RASTERIZE_VEC_HELPERS_ONLY
__kernel void rasterize_vec_prep(__global const float2 *means2d,   /* [N, 2] */
                                 __global const float *conic,      /* [N, 3] (a, b, c) */
                                 __global const float *opac,       /* [N] */
                                 __global const float *features,   /* [N, C] */
                                 const int n,
                                 __global float4 *rec)             /* [N, REC4] */
{
    const int g = get_global_id(0);
    if (g >= n) return;
    const float2 mean = means2d[g];
    const float4 cop = (float4)(conic[3 * g], conic[3 * g + 1], conic[3 * g + 2], opac[g]);
    const float thr = skip_threshold(cop.w);
    __global float4 *r = rec + g * REC4;
    r[0] = cop;
    r[1] = cull_box(mean, cop, thr);
    r[2] = (float4)(mean.x, mean.y, thr, 0.0f);
    __global float *f = (__global float *)(r + 3);
    for (int c = 0; c < 4 * (REC4 - 3); c++) f[c] = c < C ? features[g * C + c] : 0.0f;
}
#endif

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
#define FWD_BATCH TILE_PIXELS         /* Gaussians per local-memory batch */
#if FWD_BATCH % 32 != 0
#error "a work-item's hit mask is FWD_BATCH / 32 words"
#endif

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

#ifndef RASTERIZE_VEC_HELPERS_ONLY
__kernel __attribute__((reqd_work_group_size(BX, BY, 1)))
void rasterize_vec(__global const float4 *rec,       /* [N, REC4] from rasterize_vec_prep */
                   RASTER_LIST_ARGS, RASTER_FWD_OUT_ARGS)
{
    __local float2 l_mean[FWD_BATCH];
    __local float4 l_cop[FWD_BATCH];             /* (a, b, c, opac) */
    __local float l_feat[FWD_BATCH * C];
    __local float l_thr[FWD_BATCH];              /* power threshold of the early skip */
    __local float l_box[4 * FWD_BATCH];          /* cull boxes by coordinate (stage_gaussian) */
    __local int l_done[2];                       /* done-work-item counters, used alternately */

    const TileWork w = tile_work(BW, BH, tiles_x);
    const int lid = w.lid;
    const int ix0 = w.x0, iy0 = w.y0;                                  /* first pixel of the block */
    const float px0 = w.px0, px1 = px0 + (float)(BW - 1);              /* block's pixel centres */
    const float py0 = w.py0, py1 = py0 + (float)(BH - 1);

    const intV ldx = lane_dx(), ldy = lane_dy();
    const floatV px = (floatV)(px0) + convert_floatV(ldx);
    const floatV py = (floatV)(py0) + convert_floatV(ldy);
    /* lanes outside the image start done: they write nothing */
    const intV inside = (ldx + ix0 < width) & (ldy + iy0 < height);

    const int2 range = tile_ranges[w.tile];
    const int n_entries = range.y - range.x;
    const int n_batches = (n_entries + FWD_BATCH - 1) / FWD_BATCH;

    floatV T = (floatV)(1.0f);
    floatV acc[C];
    for (int c = 0; c < C; c++) acc[c] = (floatV)(0.0f);
    intV last = (intV)(0);
    intV done = ~inside;                         /* -1 where done */

#if HAVE_PREFETCH
    /* the first batch of records of the next two tiles, into L2 while this tile works: most tiles
     * have one batch, whose records its own prefetch below asks for too late to hide the gather */
    for (int nt = w.tile + 1; nt <= w.tile + 2 && nt < tiles_x * (int)get_num_groups(1); nt++) {
        const int2 nr = tile_ranges[nt];
        for (int j = lid; j < min(FWD_BATCH, nr.y - nr.x); j += N_WI)
            prefetch_record_l2(rec, sorted_values[nr.x + j]);
    }
#endif
    if (lid < 2) l_done[lid] = 0;
    barrier(CLK_LOCAL_MEM_FENCE);

    for (int b = 0; b < n_batches; b++) {
        /* Count finished work-items; the count is uniform after the barrier, so is the break. */
        if (lid == 0) l_done[(b + 1) & 1] = 0;
        if (VALL(done)) atomic_inc(&l_done[b & 1]);
        barrier(CLK_LOCAL_MEM_FENCE);
        if (l_done[b & 1] == N_WI) break;

        const int base = range.x + b * FWD_BATCH;
        const int count = min(FWD_BATCH, range.y - base);
#if HAVE_PREFETCH
        for (int j = lid; j < count; j += N_WI)   /* this work-item's records, all in flight */
            prefetch_record(rec, sorted_values[base + j]);
#endif
        for (int j = lid; j < (count + 7) / 8 * 8; j += N_WI) {
            if (j < count)
                stage_gaussian(rec, sorted_values[base + j], j, FWD_BATCH, l_mean, l_cop, l_feat, l_thr, l_box);
            else
                stage_no_box(j, FWD_BATCH, l_box);
        }
        barrier(CLK_LOCAL_MEM_FENCE);

        if (!VALL(done)) {
            /* work on copies: the originals live across barriers (PoCL keeps them in memory) */
            floatV t_cur = T;
            floatV wts[FWD_BATCH];        /* the weights alpha T of the hits that add colour, in order */
            uchar wj[FWD_BATCH];          /* and their batch entries */
            int n_add = 0;
            intV last_cur = last;
            intV done_cur = done;
            /* bit j % 32 of hits[j / 32]: entry j's cull box reaches this block */
            uint hits[FWD_BATCH / 32];
            for (int k = 0; k < FWD_BATCH / 32; k++) hits[k] = 0;
            for (int j0 = 0; j0 < count; j0 += 8)
                hits[j0 >> 5] |= box_hits8(l_box, FWD_BATCH, j0, px0, px1, py0, py1) << (j0 & 31);
            for (int k = 0; k < (count + 31) / 32 && !VALL(done_cur); k++) {
                uint bits = hits[k];
                while (bits != 0) {   /* in order: front to back */
                    const int j = 32 * k + (31 - clz1(bits & (0u - bits)));
                    bits &= bits - 1u;
                    const float4 cop = l_cop[j];
                    const float2 mean = l_mean[j];
                    const floatV dx = (floatV)(mean.x) - px;
                    const floatV dy = (floatV)(mean.y) - py;
                    /* gauss_power, lane for lane */
                    const floatV power = -0.5f * (cop.x * dx * dx + cop.z * dy * dy) - cop.y * dx * dy;
                    intV use = ~done_cur & (power <= 0.0f) & (power >= l_thr[j]);
                    if (!VANY(use)) continue;
                    const floatV raw = cop.w * vexp_nonpos(power);
                    const floatV alpha = raw < ALPHA_MAX ? raw : (floatV)(ALPHA_MAX);
                    use &= alpha >= ALPHA_MIN;
                    const floatV t_next = t_cur * (1.0f - alpha);
                    const intV stop = use & (t_next < T_STOP);
                    done_cur |= stop;
                    use &= ~stop;
                    const floatV w = use != 0 ? alpha * t_cur : (floatV)(0.0f);
                    wts[n_add] = w;
                    wj[n_add++] = (uchar)j;
                    t_cur = use != 0 ? t_next : t_cur;
                    last_cur = use != 0 ? (intV)(b * FWD_BATCH + j + 1) : last_cur;
                    if (VANY(stop) && VALL(done_cur)) break;   /* only a stop can finish the block */
                }
            }
            /* The colour sums, after the walk: the same additions in the same order per channel as
             * if made hit by hit, but with the C accumulators in registers (the walk itself needs
             * too many for them, and an accumulator in memory makes a chain through the stores). */
            floatV a[C];
            for (int c = 0; c < C; c++) a[c] = acc[c];
            for (int h = 0; h < n_add; h++) {
                const floatV wh = wts[h];
                __local const float *f = l_feat + wj[h] * C;
#pragma unroll
                for (int c = 0; c < C; c++) a[c] += f[c] * wh;
            }
            for (int c = 0; c < C; c++) acc[c] = a[c];
            T = t_cur;
            last = last_cur;
            done = done_cur;
        }
        barrier(CLK_LOCAL_MEM_FENCE);   /* the next batch overwrites the local arrays */
    }

    /* lanes to pixels */
    float T_l[VW], acc_l[VW * C];
    int last_l[VW], in_l[VW];
    vstoreF(T, 0, T_l);
    for (int c = 0; c < C; c++) vstoreF(acc[c], c, acc_l);
    vstoreI(last, 0, last_l);
    vstoreI(inside, 0, in_l);
    for (int l = 0; l < VW; l++) {
        if (in_l[l]) {
            const int p = (iy0 + l / BW) * width + ix0 + l % BW;
            for (int c = 0; c < C; c++) out[p * C + c] = acc_l[c * VW + l];
            alpha_out[p] = 1.0f - T_l[l];
            t_final[p] = T_l[l];
            last_out[p] = last_l[l];
        }
    }
}
#endif  /* RASTERIZE_VEC_HELPERS_ONLY */
