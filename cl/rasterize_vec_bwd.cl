/* Tile rasterizer, adjoint, explicit-SIMD variant for CPU OpenCL drivers (docs/ARCHITECTURE.md
 * "rasterize").  OpenCL C 1.2.
 *
 * Same maths as rasterize_bwd.cl (the GPU path; see its header for the formulas), with the work
 * layout of rasterize_vec.cl: one work-group of BX x BY work-items per tile, work-item (lx, ly)
 * owns a block of BW x BH = VW pixels (lane l: pixel (l % BW, l / BW) of the block at
 * (tx * TILE + lx * BW, ty * TILE + ly * BH)) in the lanes of floatVW vectors.
 * The group walks the tile's list back to front, from the tile's largest `last` down to entry 0, in
 * batches of BATCH Gaussians staged in local memory; a lane takes part for the entries before its
 * own `last`.  Per lane the skip tests are those of the forward pass (same helpers, vexp_nonpos ==
 * exp_nonpos bit for bit), so the same Gaussians count as contributors.
 *
 * Reduction, without atomics in local memory and without a barrier per Gaussian: for each entry j
 * of the batch each work-item whose lanes use it sums their NV gradient terms (vhsum: fixed order)
 * and stores them to its own slot l_part[j][k][work-item] (the other slots hold zeros); after the
 * batch, one work-item per (j, k) sums the N_WI slots in work-item order, zeroes them for the next
 * batch, and adds the total to the global
 * gradient with one atomic_add_global_f (skipped when 0), or, with -DDETERMINISTIC=1, stores it to
 * the entry's binning slot of v_entry (binned_slot in common.h) for rasterize_bwd_gather (in
 * rasterize_bwd.cl): bit-identical between runs.
 *
 * Build options: -DC, -DALPHA_MAX, -DALPHA_MIN, -DVW, -DBATCH (Gaussians per batch: the host picks
 * the largest that fits local memory, since l_part holds BATCH * NV * N_WI floats), -DDETERMINISTIC.
 */
#include "common.h"
#include "vexp.h"
#define RASTERIZE_VEC_HELPERS_ONLY
#include "rasterize_vec.cl"   /* REC4, stage_gaussian; gauss_power, skip_threshold, cull_box, ... */

#ifndef DETERMINISTIC
#define DETERMINISTIC 0
#endif
#define NV (6 + C)             /* gradient values per Gaussian: mean (2), conic (3), opac (1), features (C) */
#ifndef BATCH
#define BATCH 16
#endif
#if (N_WI % 16) != 0
#error "the reduction reads N_WI / 4 float4 in groups of four"
#endif

__kernel __attribute__((reqd_work_group_size(BX, BY, 1)))
void rasterize_vec_bwd(__global const float4 *rec,       /* [N, REC4] from rasterize_vec_prep */
                       __global const int *sorted_values,/* [M] */
                       __global const int2 *tile_ranges, /* [n_tiles] */
                       const int width, const int height, const int tiles_x,
                       __global const float *t_final,    /* [H, W] */
                       __global const int *last_in,      /* [H, W] */
                       __global const float *v_out,      /* [H, W, C] */
                       __global const float *v_alpha,    /* [H, W] */
                       volatile __global float *v_means2d,  /* [N, 2]  accumulated (+=) */
                       volatile __global float *v_conic,    /* [N, 3] */
                       volatile __global float *v_opac,     /* [N] */
                       volatile __global float *v_features, /* [N, C] */
                       __global float *v_entry,          /* [M, NV] per-entry terms (DETERMINISTIC only) */
                       __global const int4 *rect,        /* [N] binning rects (DETERMINISTIC only) */
                       __global const int *offsets)      /* [N + 1] binning offsets (DETERMINISTIC only) */
{
    __local float2 l_mean[BATCH];
    __local float4 l_cop[BATCH];                 /* (a, b, c, opac) */
    __local float l_feat[BATCH * C];
    __local int l_gid[BATCH];
    __local float l_thr[BATCH];
    __local float4 l_box[BATCH];                 /* cull box (xmin, xmax, ymin, ymax) */
    __local float4 l_part4[BATCH * NV * N_WI / 4];   /* [BATCH, NV, N_WI] per-work-item sums */
    __local float *l_part = (__local float *)l_part4;
    __local int l_max_last;

    const int lx = get_local_id(0), ly = get_local_id(1);
    const int lid = ly * BX + lx;
    const int tx = get_group_id(0), ty = get_group_id(1);
    const int tile = ty * tiles_x + tx;
    const int ix0 = tx * TILE + lx * BW, iy0 = ty * TILE + ly * BH;   /* first pixel of the block */
    const float px0 = (float)ix0 + 0.5f, px1 = px0 + (float)(BW - 1);   /* block's pixel centres */
    const float py0 = (float)iy0 + 0.5f, py1 = py0 + (float)(BH - 1);

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
    const floatV T_fin = vloadV(0, tf_l);
    const intV last = vloadV(0, last_l);
    const floatV va_tf = vloadV(0, va_l) * T_fin;    /* v_alpha T_final */
    floatV vo[C], S[C];
    for (int c = 0; c < C; c++) { vo[c] = vloadV(c, vo_l); S[c] = (floatV)(0.0f); }
    floatV T = T_fin;

    const int2 range = tile_ranges[tile];
    if (lid == 0) l_max_last = 0;
    for (int t = lid; t < BATCH * NV * N_WI / 4; t += N_WI) l_part4[t] = (float4)(0.0f);
    barrier(CLK_LOCAL_MEM_FENCE);
    if (max_last_mine > 0) atomic_max(&l_max_last, max_last_mine);
    barrier(CLK_LOCAL_MEM_FENCE);
    const int max_last = l_max_last;                          /* uniform */
    const int n_batches = (max_last + BATCH - 1) / BATCH;

    for (int b = n_batches - 1; b >= 0; b--) {
        const int base = range.x + b * BATCH;
        const int count = min(BATCH, max_last - b * BATCH);  /* entries of this batch to walk */
        for (int j = lid; j < count; j += N_WI) {
            const int g = sorted_values[base + j];
            l_gid[j] = g;
            stage_gaussian(rec, g, j, l_mean, l_cop, l_feat, l_thr, l_box);
        }
        barrier(CLK_LOCAL_MEM_FENCE);

        {   /* work on copies: the originals live across barriers (PoCL keeps them in memory) */
            floatV t_cur = T;
            floatV s_cur[C];
            for (int c = 0; c < C; c++) s_cur[c] = S[c];
            /* the batch entries whose cull box reaches this block, in order (branch-free) */
            uchar hits[BATCH];
            int n_hits = 0;
            for (int j = 0; j < count; j++) {
                const float4 bb = l_box[j];
                hits[n_hits] = (uchar)j;
                n_hits += (bb.x <= px1) & (bb.y >= px0) & (bb.z <= py1) & (bb.w >= py0);
            }
            for (int h = n_hits - 1; h >= 0; h--) {
                const int j = hits[h];
                __local float *part = l_part + j * NV * N_WI + lid;   /* slot (j, k) at k * N_WI */
                {
                    const float4 cop = l_cop[j];
                    const float2 mean = l_mean[j];
                    const floatV dx = (floatV)(mean.x) - px;
                    const floatV dy = (floatV)(mean.y) - py;
                    const floatV power = -0.5f * (cop.x * dx * dx + cop.z * dy * dy) - cop.y * dx * dy;
                    intV use = ((intV)(b * BATCH + j) < last) & (power <= 0.0f) & (power >= l_thr[j]);
                    if (VANY(use)) {
                        const floatV G = vexp_nonpos(power <= 0.0f ? power : (floatV)(0.0f));
                        const floatV raw = cop.w * G;
                        const floatV alpha = raw < ALPHA_MAX ? raw : (floatV)(ALPHA_MAX);
                        use &= alpha >= ALPHA_MIN;
                        if (VANY(use)) {
                            const floatV inv_om = 1.0f / (1.0f - alpha);
                            t_cur = use != 0 ? t_cur * inv_om : t_cur;   /* T in front of j */
                            const floatV w = use != 0 ? alpha * t_cur : (floatV)(0.0f);
                            floatV v_al = va_tf * inv_om;              /* d L / d alpha_j */
                            for (int c = 0; c < C; c++) {
                                const float f = l_feat[j * C + c];
                                v_al += vo[c] * (f * t_cur - s_cur[c] * inv_om);
                                s_cur[c] += f * w;
                                part[(6 + c) * N_WI] = vhsum(vo[c] * w);
                            }
                            /* the ALPHA_MAX clamp blocks the gradient to power and opac */
                            const intV grad = use & (raw <= ALPHA_MAX);
                            const floatV v_power = grad != 0 ? v_al * alpha : (floatV)(0.0f);
                            part[0 * N_WI] = vhsum(-v_power * (cop.x * dx + cop.y * dy));
                            part[1 * N_WI] = vhsum(-v_power * (cop.z * dy + cop.y * dx));
                            part[2 * N_WI] = vhsum(-0.5f * v_power * dx * dx);
                            part[3 * N_WI] = vhsum(-v_power * dx * dy);
                            part[4 * N_WI] = vhsum(-0.5f * v_power * dy * dy);
                            part[5 * N_WI] = vhsum(grad != 0 ? v_al * G : (floatV)(0.0f));
                        }
                    }
                }
            }
            T = t_cur;
            for (int c = 0; c < C; c++) S[c] = s_cur[c];
        }
        barrier(CLK_LOCAL_MEM_FENCE);

        /* one work-item per (entry, value): sum the work-items' slots in order, one global add */
        for (int t = lid; t < count * NV; t += N_WI) {
            /* float4 loads into four accumulators (a fixed order; serial scalar adds are
             * latency-bound on CPUs) */
            __local float4 *src = l_part4 + t * (N_WI / 4);
            float4 s0 = src[0], s1 = src[1], s2 = src[2], s3 = src[3];
            for (int i = 4; i < N_WI / 4; i += 4) {
                s0 += src[i]; s1 += src[i + 1]; s2 += src[i + 2]; s3 += src[i + 3];
            }
            for (int i = 0; i < N_WI / 4; i++) src[i] = (float4)(0.0f);   /* zeros for the next batch */
            const float4 s4 = (s0 + s1) + (s2 + s3);
            const float sum = (s4.x + s4.y) + (s4.z + s4.w);
            const int j = t / NV, k = t % NV;
#if DETERMINISTIC
            const int u = binned_slot(rect, offsets, l_gid[j], tx, ty);
            if (u >= 0) v_entry[u * NV + k] = sum;   /* this group's alone */
#else
            if (sum != 0.0f) {
                const int g = l_gid[j];
                volatile __global float *dst =
                    k < 2 ? v_means2d + 2 * g + k :
                    k < 5 ? v_conic + 3 * g + (k - 2) :
                    k == 5 ? v_opac + g : v_features + g * C + (k - 6);
                atomic_add_global_f(dst, sum);
            }
#endif
        }
        barrier(CLK_LOCAL_MEM_FENCE);   /* the next batch overwrites the batch arrays and l_part */
    }
}
