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
 * lane the compositing is exactly that of rasterize.cl (the blend step of blend.h, written once for
 * float and floatVW; vexp_nonpos equals exp_nonpos bit for bit): skip power > 0, alpha = min(ALPHA_MAX, opac G),
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
#include "blend.h"        /* the blend step, skip_threshold, cull_box */
#include "raster_vec.h"   /* BW, BH, BX, BY, N_WI, lane_dx, REC4, stage_gaussian, box_hits8 */

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

#define FWD_BATCH TILE_PIXELS         /* Gaussians per local-memory batch */
#if FWD_BATCH % 32 != 0
#error "a work-item's hit mask is FWD_BATCH / 32 words"
#endif

__kernel __attribute__((reqd_work_group_size(BX, BY, 1)))
void rasterize_vec(__global const float4 *rec,       /* [N, REC4] from rasterize_vec_prep */
                   RASTER_LIST_ARGS, RASTER_FWD_OUT_ARGS)
{
    RASTER_BATCH_LOCALS(FWD_BATCH);
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
                    const floatV power = blend_power_v(cop, dx, dy);   /* blend.h */
                    intV use = ~done_cur & (power <= 0.0f) & (power >= l_thr[j]);
                    if (!VANY(use)) continue;
                    const floatV alpha = blend_alpha_v(cop.w, blend_G_v(power));
                    use &= alpha >= ALPHA_MIN;
                    const floatV t_next = blend_behind_v(t_cur, alpha);
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
