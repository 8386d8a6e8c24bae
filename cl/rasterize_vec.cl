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
 * lanes are done, and the group stops loading batches once every work-item is done.
 *
 * Culling (exact, as in rasterize.cl): per batch, each culling block (BROWS work-item blocks one
 * above the other) gets the ordered list of the batch's Gaussians whose cull box reaches one of its
 * pixel centres; a work-item walks its list, skips entries whose box misses its block's rows, and
 * masks lanes whose power is below the skip threshold.  Every work-item reaches every barrier.
 *
 * Build options: -DC, -DALPHA_MAX, -DALPHA_MIN, -DT_STOP (as rasterize.cl), -DVW=<2|4|8|16>,
 * -DBW (block width, divides VW), -DBROWS (work-item block rows per culling list).
 */
#include "common.h"
#include "vexp.h"
#define RASTERIZE_HELPERS_ONLY
#include "rasterize.cl"   /* gauss_power, exp_nonpos, skip_threshold, cull_box */

/* Per-Gaussian record, written once per call by rasterize_vec_prep (one Gaussian per work-item)
 * and gathered per tile entry by the rasterize_vec kernels: one contiguous read instead of four
 * scattered arrays, and the skip threshold (a log) and cull box (two sqrt) computed once per Gaussian
 * instead of once per tile entry.  REC4 float4 per Gaussian:
 *   [0] (a, b, c, opac)   [1] cull box (xmin, xmax, ymin, ymax)   [2] (mean x, mean y, thr, 0)
 *   [3 ..] features[0 .. C-1], zero-padded to a multiple of 4. */
#define REC4 (3 + (C + 3) / 4)

inline void stage_gaussian(__global const float4 *rec, int g, int j, __local float2 *l_mean,
                           __local float4 *l_cop, __local float *l_feat, __local float *l_thr,
                           __local float4 *l_box) {
    __global const float4 *r = rec + g * REC4;
    l_cop[j] = r[0];
    l_box[j] = r[1];
    const float4 m = r[2];
    l_mean[j] = m.xy;
    l_thr[j] = m.z;
    __global const float *f = (__global const float *)(r + 3);
    for (int c = 0; c < C; c++) l_feat[j * C + c] = f[c];
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
#define FWD_BATCH TILE_PIXELS         /* Gaussians per local-memory batch (indices fit a uchar) */
#ifndef BROWS
#define BROWS 4                       /* rows of blocks that share a culling list */
#endif
#if (BY % BROWS) != 0
#error "BROWS must divide TILE / BH"
#endif
#define N_BLK (BX * (BY / BROWS))     /* culling lists per tile (<= N_WI) */

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
    RASTER_BATCH_LOCALS(FWD_BATCH);
    __local uchar l_list[N_BLK * FWD_BATCH];     /* per culling-block lists of batch indices */
    __local int l_len[N_BLK];
    __local int l_done[2];                       /* done-work-item counters, used alternately */

    const TileWork w = tile_work(BW, BH, tiles_x);
    const int lx = w.lx, ly = w.ly, lid = w.lid, tx = w.tx, ty = w.ty;
    const int ix0 = w.x0, iy0 = w.y0;                                  /* first pixel of the block */
    const float px0 = w.px0, px1 = px0 + (float)(BW - 1);              /* block's pixel centres */
    const float py0 = w.py0, py1 = py0 + (float)(BH - 1);
    const int my_blk = (ly / BROWS) * BX + lx;

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
        for (int j = lid; j < count; j += N_WI) {   /* this work-item's records, all in flight */
            __global const float4 *r = rec + sorted_values[base + j] * REC4;
            PREFETCH(r);
            PREFETCH(r + REC4 - 1);
        }
#endif
        for (int j = lid; j < count; j += N_WI)
            stage_gaussian(rec, sorted_values[base + j], j, l_mean, l_cop, l_feat, l_thr, l_box);
        barrier(CLK_LOCAL_MEM_FENCE);
        if (lid < N_BLK) {   /* list of the batch entries whose cull box reaches culling block lid */
            const float bx0 = (float)(tx * TILE + (lid % BX) * BW) + 0.5f, bx1 = bx0 + (float)(BW - 1);
            const float by0 = (float)(ty * TILE + (lid / BX) * BROWS * BH) + 0.5f;
            const float by1 = by0 + (float)(BROWS * BH - 1);
            __local uchar *list = l_list + lid * FWD_BATCH;
            int n = 0;
            for (int j = 0; j < count; j++) {
                const float4 bb = l_box[j];
                list[n] = (uchar)j;   /* branch-free append: kept when the box reaches the block */
                n += (bb.x <= bx1) & (bb.y >= bx0) & (bb.z <= by1) & (bb.w >= by0);
            }
            l_len[lid] = n;
        }
        barrier(CLK_LOCAL_MEM_FENCE);

        const int n_mine = l_len[my_blk];
        __local const uchar *mine = l_list + my_blk * FWD_BATCH;
        if (!VALL(done)) {
            /* work on copies: the originals live across barriers (PoCL keeps them in memory) */
            floatV t_cur = T;
            floatV a_cur[C];
            for (int c = 0; c < C; c++) a_cur[c] = acc[c];
            intV last_cur = last;
            intV done_cur = done;
            /* the list's entries whose box reaches this block's rows (the list tested x), in
             * order, appended branch-free */
            uchar hits[FWD_BATCH];
            int n_hits = 0;
            for (int i = 0; i < n_mine; i++) {
                const int j = mine[i];
                const float4 bb = l_box[j];
                hits[n_hits] = (uchar)j;
                n_hits += (bb.z <= py1) & (bb.w >= py0);
            }
            for (int h = 0; h < n_hits; h++) {
                const int j = hits[h];
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
                for (int c = 0; c < C; c++) a_cur[c] += l_feat[j * C + c] * w;
                t_cur = use != 0 ? t_next : t_cur;
                last_cur = use != 0 ? (intV)(b * FWD_BATCH + j + 1) : last_cur;
                if (VALL(done_cur)) break;
            }
            T = t_cur;
            for (int c = 0; c < C; c++) acc[c] = a_cur[c];
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
