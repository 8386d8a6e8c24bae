/* Tile rasterizer, adjoint, explicit-SIMD variant for CPU OpenCL drivers (docs/ARCHITECTURE.md
 * "rasterize").  OpenCL C 1.2.
 *
 * Same maths as rasterize_bwd.cl (the GPU path; see its header for the formulas), with the work
 * layout of rasterize_vec.cl: one work-group of BX x BY work-items per tile, work-item (lx, ly)
 * owns a block of BW x BH = VW pixels (lane l: pixel (l % BW, l / BW) of the block at
 * (tx * TILE + lx * BW, ty * TILE + ly * BH)) in the lanes of floatVW vectors.
 * The group walks the tile's list back to front, from the tile's largest `last` down to entry 0, in
 * batches of BATCH Gaussians staged in local memory; a lane takes part for the entries before its
 * own `last`.  Per lane the skip tests are those of the forward pass (the blend step of blend.h,
 * vexp_nonpos == exp_nonpos bit for bit), so the same Gaussians count as contributors.
 *
 * Per batch, the walk over the work-item's hits (back to front) carries T and D and keeps, for each
 * hit that adds, the weights alpha T and the two terms that need the carried values; the gradient
 * terms of the kept hits and their lane sums follow in a second loop, which carries nothing (the
 * same operations on the same values, so the same bits as doing them in the walk).
 *
 * Reduction, without atomics in local memory and without a barrier per Gaussian: for each entry j
 * of the batch, each work-item whose lanes use it sums its lanes' NV gradient terms (lane_sum8, a
 * fixed order) and stores them as NSV float4 to its own slot l_part4[j][work-item], and marks bit j
 * of its mask l_wrote[work-item].  After the batch, one work-item per entry adds up the slots that
 * were written, in work-item order (float4 adds; an unwritten slot, stale, is added as +0, which
 * changes no sum, so no slot needs zeroing), and adds the totals to
 * the global gradients with atomic_add_global_f (skipped when 0), or, with -DDETERMINISTIC=1,
 * stores them to v_entry at the entry's sorted position for rasterize_bwd_gather (in
 * rasterize_bwd.cl), which sums them per Gaussian in binning order: bit-identical between runs.
 *
 * Build options: -DC, -DALPHA_MAX, -DALPHA_MIN, -DVW, -DBATCH (Gaussians per batch: the host picks
 * the largest that fits local memory, since l_part4 holds BATCH * N_WI * NSV float4), -DDETERMINISTIC.
 */
#include "blend.h"        /* the blend step (forward and adjoint) */
#include "raster_vec.h"   /* BW, BH, BX, BY, N_WI, lane_dx, REC4, stage_gaussian, box_hits8 */

#ifndef DETERMINISTIC
#define DETERMINISTIC 0
#endif
#define NV (6 + C)             /* gradient values per Gaussian: mean (2), conic (3), opac (1), features (C) */
#define NSV ((NV + 3) / 4)     /* float4 per slot (the terms past NV are zeros) */
#ifndef BATCH
#define BATCH 16
#endif
#if BATCH > 64 || BATCH % 8 != 0
#error "a work-item's hit and written-slot masks are one word per batch (at most 64 bits), tested 8 entries at a time"
#endif
#if BATCH > 32
typedef ulong bmask;           /* a bit per entry of a batch */
#define MASK_TOP(m) (63 - clz64(m))
#else
typedef uint bmask;
#define MASK_TOP(m) (31 - clz1(m))
#endif

/* The lane sums of a hit's gradient terms, in the order of vhsum4 (vexp.h) value for value, so the
 * same bits: at 16 lanes s = v.lo + v.hi, then the adjacent pairs of s, then the pairs of those
 * (s0 + s1) + (s2 + s3) and (s4 + s5) + (s6 + s7), then their sum.  Done for 8 (or 4) terms at
 * once in the lane layout of x86's horizontal add (hadd8), which needs no reordering between the
 * levels: about half the shuffles of one vhsum4 per 4 terms.  Elsewhere vhsum4 itself. */
#if VW == 16
inline float8 hadd8(float8 x, float8 y) {   /* (x0+x1, x2+x3, y0+y1, y2+y3, x4+x5, x6+x7, y4+y5, y6+y7) */
    return (float8)(x.s02, y.s02, x.s46, y.s46) + (float8)(x.s13, y.s13, x.s57, y.s57);
}
/* lanes 0-3: (s0 + s1) + (s2 + s3) of a, b, c, d; lanes 4-7: (s4 + s5) + (s6 + s7) of each */
inline float8 hsum_quad(float16 a, float16 b, float16 c, float16 d) {
    return hadd8(hadd8(a.lo + a.hi, b.lo + b.hi), hadd8(c.lo + c.hi, d.lo + d.hi));
}
inline float4 lane_sum4(float16 a, float16 b, float16 c, float16 d) {
    const float8 x = hsum_quad(a, b, c, d);
    return x.lo + x.hi;
}
inline float8 lane_sum8(float16 a, float16 b, float16 c, float16 d, float16 e, float16 f, float16 g,
                        float16 h) {
    const float8 x = hsum_quad(a, b, c, d), y = hsum_quad(e, f, g, h);
    return (float8)(x.lo, y.lo) + (float8)(x.hi, y.hi);
}
#else
#define lane_sum4 vhsum4
inline float8 lane_sum8(floatV a, floatV b, floatV c, floatV d, floatV e, floatV f, floatV g, floatV h) {
    return (float8)(vhsum4(a, b, c, d), vhsum4(e, f, g, h));
}
#endif

__kernel __attribute__((reqd_work_group_size(BX, BY, 1)))
void rasterize_vec_bwd(__global const float4 *rec,       /* [N, REC4] from rasterize_vec_prep */
                       RASTER_LIST_ARGS, RASTER_BWD_ARGS)
{
    RASTER_BATCH_LOCALS(BATCH);
    __local int l_gid[BATCH];
    __local float l_box[4 * BATCH];              /* cull boxes by coordinate: xmin[BATCH], xmax, ymin, ymax */
    __local float4 l_part4[BATCH * N_WI * NSV];  /* [BATCH, N_WI, NSV] per-work-item sums */
    __local bmask l_wrote[N_WI];                 /* bit j: the work-item wrote its slot of entry j */
    __local int l_max_last;

    const TileWork w = tile_work(BW, BH, tiles_x);
    const int lid = w.lid, tx = w.tx, ty = w.ty;
    const int ix0 = w.x0, iy0 = w.y0;                                  /* first pixel of the block */
    const float px0 = w.px0, px1 = px0 + (float)(BW - 1);              /* block's pixel centres */
    const float py0 = w.py0, py1 = py0 + (float)(BH - 1);

    /* per-lane inputs; lanes outside the image: T_final 1, last 0, no cotangent */
    float tf_l[VW], va_l[VW], vo_l[C * VW];
    int last_l[VW];
    int max_last_mine = 0;
    for (int l = 0; l < VW; l++) {
        const int ix = ix0 + l % BW, iy = iy0 + l / BW;
        const bool in = ix < width && iy < height;
        const int p = iy * width + ix;
        tf_l[l] = in ? t_final[p] : 1.0f;
        last_l[l] = in ? last_in[p] : 0;
        va_l[l] = in ? v_alpha[p] : 0.0f;
        for (int c = 0; c < C; c++) vo_l[c * VW + l] = in ? v_out[p * C + c] : 0.0f;
        max_last_mine = max(max_last_mine, last_l[l]);
    }
    const floatV px = (floatV)(px0) + convert_floatV(lane_dx());
    const floatV py = (floatV)(py0) + convert_floatV(lane_dy());
    const floatV T_fin = vloadF(0, tf_l);
    const intV last = vloadI(0, last_l);
    const floatV va_tf = vloadF(0, va_l) * T_fin;    /* v_alpha T_final */
    floatV vo[C];
    for (int c = 0; c < C; c++) vo[c] = vloadF(c, vo_l);
    /* D = sum_c vo_c S_c, S_c the colour composited behind the current entry: the adjoint needs
     * the S_c only in this combination, so one running value replaces the C of them */
    floatV D = (floatV)(0.0f);
    floatV T = T_fin;

    const int2 range = tile_ranges[w.tile];
    const int max_last = group_max_last(max_last_mine, lid, &l_max_last);   /* uniform */
    const int n_batches = (max_last + BATCH - 1) / BATCH;

#if HAVE_PREFETCH
    /* the first batch walked (the last one), whose records nothing else has asked for yet; each
     * batch then asks for the next one's while it is staged (below) */
    for (int j = max(n_batches - 1, 0) * BATCH + lid; j < max_last; j += N_WI)
        prefetch_record(rec, sorted_values[range.x + j]);
#endif
    for (int b = n_batches - 1; b >= 0; b--) {
        const int base = range.x + b * BATCH;
        const int count = min(BATCH, max_last - b * BATCH);  /* entries of this batch to walk */
        for (int j = lid; j < BATCH; j += N_WI) {
            if (j < count) {
                const int g = sorted_values[base + j];
                l_gid[j] = g;
                stage_gaussian(rec, g, j, BATCH, l_mean, l_cop, l_feat, l_thr, l_box);
            } else {   /* past the walk */
                stage_no_box(j, BATCH, l_box);
            }
        }
#if HAVE_PREFETCH
        if (b > 0)   /* the next batch walked (b - 1, full): its records' two cache lines */
            for (int j = lid; j < BATCH; j += N_WI)
                prefetch_record(rec, sorted_values[base - BATCH + j]);
#endif
        barrier(CLK_LOCAL_MEM_FENCE);

        {   /* work on copies: the originals live across barriers (PoCL keeps them in memory) */
            floatV t_cur = T;
            floatV d_cur = D;
            /* bit j: batch entry j's cull box reaches this block (8 entries per test); walked
             * from the highest bit down, back to front */
            bmask hitmask = 0;
            for (int j0 = 0; j0 < count; j0 += 8)
                hitmask |= (bmask)box_hits8(l_box, BATCH, j0, px0, px1, py0, py1) << j0;
            bmask wrote = 0;
            /* the walk (back to front) carries T and D; it keeps, per hit that adds, the values the
             * gradient terms need, and the terms and their lane sums follow per kept hit */
            floatV k_w[BATCH], k_vp[BATCH], k_vg[BATCH];
            uchar k_j[BATCH];
            int n_kept = 0;
            while (hitmask != 0) {
                const int j = MASK_TOP(hitmask);
                hitmask ^= (bmask)1 << j;
                const float4 cop = l_cop[j];
                const float2 mean = l_mean[j];
                const floatV dx = (floatV)(mean.x) - px;
                const floatV dy = (floatV)(mean.y) - py;
                const floatV power = blend_power_v(cop, dx, dy);   /* blend.h */
                intV use = lane_mask((intV)(b * BATCH + j) < last) & lane_mask(power <= 0.0f) &
                           lane_mask(power >= l_thr[j]);   /* lane_mask: vexp.h */
                if (!VANY(use)) continue;
                const floatV G = blend_G_v(power <= 0.0f ? power : (floatV)(0.0f));
                const floatV alpha = blend_alpha_v(cop.w, G);
                use &= lane_mask(alpha >= ALPHA_MIN);
                if (!VANY(use)) continue;
                const floatV inv_om = blend_inv_om_v(alpha);
                t_cur = use != 0 ? t_cur * inv_om : t_cur;   /* T in front of j */
                const floatV w = use != 0 ? alpha * t_cur : (floatV)(0.0f);
                /* d L / d alpha_j = (v_alpha T_final - D) / (1 - alpha) + T_j sum_c vo_c f_c */
                floatV dot = (floatV)(0.0f);
#pragma unroll
                for (int c = 0; c < C; c++) dot += vo[c] * l_feat[j * C + c];
                const floatV v_al = (va_tf - d_cur) * inv_om + t_cur * dot;
                d_cur += dot * w;
                /* the ALPHA_MAX clamp blocks the gradient to power and opac */
                const intV grad = use & lane_mask(blend_open_v(cop.w, G));
                k_w[n_kept] = w;
                k_vp[n_kept] = grad != 0 ? v_al * alpha : (floatV)(0.0f);
                k_vg[n_kept] = grad != 0 ? v_al * G : (floatV)(0.0f);
                k_j[n_kept++] = (uchar)j;
                wrote |= (bmask)1 << j;
            }
            for (int h = 0; h < n_kept; h++) {
                const int j = k_j[h];
                __local float4 *slot = l_part4 + (j * N_WI + lid) * NSV;
                const float4 cop = l_cop[j];
                const float2 mean = l_mean[j];
                const floatV dx = (floatV)(mean.x) - px;
                const floatV dy = (floatV)(mean.y) - py;
                const floatV w = k_w[h], v_power = k_vp[h];
                floatV term[4 * NSV];   /* per-lane gradient terms, zeros past NV */
                blend_power_grad_v(v_power, cop, dx, dy, term);
                term[5] = k_vg[h];
#pragma unroll
                for (int c = 0; c < C; c++) term[6 + c] = vo[c] * w;
#pragma unroll
                for (int k = NV; k < 4 * NSV; k++) term[k] = (floatV)(0.0f);
#pragma unroll
                for (int v = 0; v + 1 < NSV; v += 2) {   /* 8 terms at a time */
                    const float8 s = lane_sum8(term[4 * v], term[4 * v + 1], term[4 * v + 2],
                                               term[4 * v + 3], term[4 * v + 4], term[4 * v + 5],
                                               term[4 * v + 6], term[4 * v + 7]);
                    slot[v] = s.lo;
                    slot[v + 1] = s.hi;
                }
#if NSV % 2
                slot[NSV - 1] = lane_sum4(term[4 * NSV - 4], term[4 * NSV - 3], term[4 * NSV - 2],
                                          term[4 * NSV - 1]);
#endif
            }
            l_wrote[lid] = wrote;
            T = t_cur;
            D = d_cur;
        }
        barrier(CLK_LOCAL_MEM_FENCE);

        /* one work-item per entry: sum the slots the work-items wrote, in work-item order; one
         * global add or store per value */
        for (int j = lid; j < count; j += N_WI) {
            __local const float4 *src = l_part4 + j * N_WI * NSV;
            float4 sum[NSV];
#pragma unroll
            for (int v = 0; v < NSV; v++) sum[v] = (float4)(0.0f);
            /* branch-free: a slot not written this batch (stale) adds +0, which leaves every sum
             * as it was (a sum from +0 is never -0), so the same bits as skipping it */
            for (int i = 0; i < N_WI; i++) {
                const int4 keep = (int4)(-(int)((l_wrote[i] >> j) & 1));
#pragma unroll
                for (int v = 0; v < NSV; v++) sum[v] += as_float4(as_int4(src[i * NSV + v]) & keep);
            }
#if DETERMINISTIC && NV % 4 == 0   /* whole float4 rows (16-byte aligned) */
            __global float4 *dst = (__global float4 *)(v_entry + (base + j) * NV);   /* sorted entry: ours alone */
#pragma unroll
            for (int v = 0; v < NSV; v++) dst[v] = sum[v];
#elif DETERMINISTIC
            const float *tot = (const float *)sum;   /* [4 * NSV], the NV values first */
            for (int k = 0; k < NV; k++) v_entry[(base + j) * NV + k] = tot[k];
#else
            const float *tot = (const float *)sum;
            for (int k = 0; k < NV; k++)
                add_gradient(k, l_gid[j], tot[k], v_means2d, v_conic, v_opac, v_features);
#endif
        }
        barrier(CLK_LOCAL_MEM_FENCE);   /* the next batch overwrites the batch arrays, l_part4, l_wrote */
    }
#if DETERMINISTIC
    /* the entries past the walk (no pixel reaches them): zero terms, so that v_entry needs no fill */
    for (int j = max_last + lid; j < range.y - range.x; j += N_WI)
        for (int k = 0; k < NV; k++) v_entry[(range.x + j) * NV + k] = 0.0f;
#endif
}
