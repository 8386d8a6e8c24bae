/* Tile rasterizer, adjoint (docs/ARCHITECTURE.md "rasterize").  OpenCL C 1.2.
 *
 * Same work layout as rasterize.cl: one TILE x TILE work-group per tile, one pixel per work-item.
 * The group walks the tile's list back to front, from the tile's largest `last` down to the first
 * entry, in batches of BATCH Gaussians staged in local memory; a pixel takes part for the entries
 * before its own last contributor (last[p] - 1 down to 0).
 *
 * Transmittance is recovered by division, as in 3DGS: starting from T = T_final, for each
 * contributor k (back to front) T_k = T_{k+1} / (1 - alpha_k); alpha_k <= ALPHA_MAX keeps the
 * divisor >= 1 - ALPHA_MAX.  The skip tests (power > 0, alpha < ALPHA_MIN) use the same blend step
 * as the forward kernel (blend.h), so the same Gaussians count as contributors.
 *
 * With S_c = sum_{j behind k} f_jc alpha_j T_j (the colour composited behind k):
 *   d out_c / d alpha_k     = f_kc T_k - S_c / (1 - alpha_k)
 *   d alpha_pix / d alpha_k = T_final / (1 - alpha_k)            (alpha_pix = 1 - T_final)
 *   d out_c / d f_kc        = alpha_k T_k
 * and alpha_k = opac_k G_k (G_k = exp(power)) unless the ALPHA_MAX clamp is active, where the
 * gradient to opac and power is zero.
 *
 * Reduction, without local atomics: the Gaussians of a batch are taken one at a time (a loop that
 * is uniform over the group).  For Gaussian j, only the SUB x SUB sub-blocks that its cull box
 * reaches (a 16-bit mask, sub_block_mask in blend.h) take part; Gaussians that reach none are skipped by
 * the whole group.  (1) each pixel of a reached sub-block writes its NV gradient terms (zeros
 * where the Gaussian is skipped) to its own slot of l_pix; (2) one work-item per (value, sub-block) sums that sub-block's 16 slots; (3) one
 * work-item per value sums the sub-block partials and adds the total to the global gradient with
 * one atomic_add_global_f.  The in-group order of the float adds is fixed; the order in which the
 * groups' atomic adds land is not, so results can differ in the last bits between runs.
 *
 * Deterministic mode (-DDETERMINISTIC=1): step (3) stores the group's total for sorted entry k
 * (Gaussian g in this tile) to v_entry[k] (entries are unique to a tile, so no atomics; the
 * stores of a tile are contiguous), and rasterize_bwd_gather sums each Gaussian's entries in its
 * binning order (its rect's tiles row-major: slot u -> entry entry_of[u], from
 * rasterize_bwd_entry_of): bit-identical results from run to run.  (Storing at the binning slot
 * instead scattered 4 (6 + C) bytes per entry over the whole array: a cache miss on each store.)
 *
 * Build options: -DC, -DALPHA_MAX, -DALPHA_MIN (set by endowave_cl/ops/rasterize.py).
 */
#include "blend.h"   /* the blend step, skip_threshold, cull_box, sub_block_mask, SUB, N_SUB */

#if SUB != 4
#error "the sub-block sums below read rows of a sub-block with vload4"
#endif

#ifndef DETERMINISTIC
#define DETERMINISTIC 0
#endif

#define NV (6 + C)   /* gradient values per Gaussian: mean (2), conic (3), opac (1), features (C) */
#define BATCH 128    /* Gaussians per batch; keeps local memory under 32 KiB (Oclgrind) for C <= 9 */

__kernel __attribute__((reqd_work_group_size(TILE, TILE, 1)))
void rasterize_bwd(__global const float2 *means2d,   /* [N, 2] */
                   __global const float *conic,      /* [N, 3] */
                   __global const float *opac,       /* [N] */
                   __global const float *features,   /* [N, C] */
                   RASTER_LIST_ARGS, RASTER_BWD_ARGS)
{
    RASTER_BATCH_LOCALS(BATCH);
    __local int l_gid[BATCH];
    __local int l_mask[BATCH];                   /* sub-blocks reached by each Gaussian */
    __local float l_pix[NV * TILE_PIXELS];       /* [NV, pixel] gradient terms of one Gaussian */
    __local float l_part[NV * N_SUB];            /* [NV, sub-block] partial sums */
    __local uchar l_act[BATCH];                  /* batch entries with a non-empty mask, in order */
    __local int l_n_act;
    __local int l_max_last;

    const TileWork w = tile_work(1, 1, tiles_x);
    const int lid = w.lid, tx = w.tx, ty = w.ty;
    const int ix = w.x0, iy = w.y0;
    const bool inside = ix < width && iy < height;
    const float px = w.px0, py = w.py0;
    const int p = iy * width + ix;
    const int my_sub = (w.ly / SUB) * SUBS_PER_ROW + w.lx / SUB;

    const int2 range = tile_ranges[w.tile];

    float T = 1.0f, T_fin = 1.0f, va = 0.0f;
    float vo[C], S[C];
    int last = 0;
    for (int c = 0; c < C; c++) { vo[c] = 0.0f; S[c] = 0.0f; }
    if (inside) {
        T_fin = t_final[p];
        T = T_fin;
        last = last_in[p];
        va = v_alpha[p];
        for (int c = 0; c < C; c++) vo[c] = v_out[p * C + c];
    }

    const int max_last = group_max_last(last, lid, &l_max_last);   /* uniform */
    const int n_batches = (max_last + BATCH - 1) / BATCH;

    for (int b = n_batches - 1; b >= 0; b--) {
        const int base = range.x + b * BATCH;
        const int count = min(BATCH, max_last - b * BATCH);  /* entries of this batch to walk */
        if (lid < count) {
            const int g = sorted_values[base + lid];
            l_gid[lid] = g;
            const float2 mean = means2d[g];
            const float4 cop = (float4)(conic[3 * g], conic[3 * g + 1], conic[3 * g + 2], opac[g]);
            l_mean[lid] = mean;
            l_cop[lid] = cop;
            for (int c = 0; c < C; c++) l_feat[lid * C + c] = features[g * C + c];
            const float thr = skip_threshold(cop.w);
            l_thr[lid] = thr;
            l_mask[lid] = sub_block_mask(cull_box(mean, cop, thr), tx * TILE, ty * TILE);
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        if (lid == 0) {   /* Gaussians no pixel of the tile can use are left out */
            int n = 0;
            for (int j = 0; j < count; j++)
                if (l_mask[j] != 0) l_act[n++] = (uchar)j;
            l_n_act = n;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        const int n_act = l_n_act;            /* uniform */

        const int j_end = last - b * BATCH;   /* this pixel takes entries j < j_end */
        for (int i = n_act - 1; i >= 0; i--) {
            const int j = l_act[i];
            const int mask = l_mask[j];
            if ((mask >> my_sub) & 1) {
                bool used = false;
                const float4 cop = l_cop[j];
                const float2 d = l_mean[j] - (float2)(px, py);
                const float power = blend_power(cop, d.x, d.y);   /* blend.h */
                if (j < j_end && power <= 0.0f && power >= l_thr[j]) {
                    const float G = blend_G(power);
                    const float alpha = blend_alpha(cop.w, G);
                    if (alpha >= ALPHA_MIN) {
                        used = true;
                        const float inv_om = blend_inv_om(alpha);
                        T = T * inv_om;                  /* transmittance in front of Gaussian j */
                        const float w = alpha * T;
                        float v_al = va * T_fin * inv_om; /* d L / d alpha_j */
                        for (int c = 0; c < C; c++) {
                            const float f = l_feat[j * C + c];
                            v_al += vo[c] * (f * T - S[c] * inv_om);
                            S[c] += f * w;
                            l_pix[(6 + c) * TILE_PIXELS + lid] = vo[c] * w;
                        }
                        float gr[6] = {0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f};
                        if (blend_open(cop.w, G)) {      /* the clamp blocks the gradient */
                            blend_power_grad(v_al * alpha, cop, d.x, d.y, gr);
                            gr[5] = v_al * G;
                        }
                        for (int k = 0; k < 6; k++) l_pix[k * TILE_PIXELS + lid] = gr[k];
                    }
                }
                if (!used)   /* a reached pixel that the Gaussian skips adds zeros */
                    for (int k = 0; k < NV; k++) l_pix[k * TILE_PIXELS + lid] = 0.0f;
            }
            barrier(CLK_LOCAL_MEM_FENCE);
            /* (2) sub-block partial sums; pixel (u, v) of sub-block s is at slot
             * (sy * SUB + v) * TILE + sx * SUB + u. */
            for (int t = lid; t < NV * N_SUB; t += TILE_PIXELS) {
                const int k = t / N_SUB, s = t % N_SUB;
                float sum = 0.0f;
                if ((mask >> s) & 1) {
                    const int o = (s / SUBS_PER_ROW) * SUB * TILE + (s % SUBS_PER_ROW) * SUB;
                    __local const float *src = l_pix + k * TILE_PIXELS + o;
                    float4 s4 = vload4(0, src);
                    for (int v = 1; v < SUB; v++) s4 += vload4(0, src + v * TILE);
                    sum = (s4.x + s4.y) + (s4.z + s4.w);
                }
                l_part[t] = sum;
            }
            barrier(CLK_LOCAL_MEM_FENCE);
            /* (3) one global add per value */
            if (lid < NV) {
                float sum = 0.0f;
                for (int s = 0; s < N_SUB; s++) sum += l_part[lid * N_SUB + s];
#if DETERMINISTIC
                v_entry[(base + j) * NV + lid] = sum;   /* sorted entry base + j: this group's alone */
#else
                add_gradient(lid, l_gid[j], sum, v_means2d, v_conic, v_opac, v_features);
#endif
            }
            /* No barrier needed here: the next iteration's step (1) rewrites l_pix, which step (3)
             * does not read; l_part is rewritten only after the next (1)->(2) barrier. */
        }
        barrier(CLK_LOCAL_MEM_FENCE);   /* the next batch overwrites the batch arrays */
    }
}

/* Deterministic mode, before the gather: entry_of[u] = k for the sorted entry k whose binning slot
 * (binned_slot in common.h) is u; entry_of must hold -1 on entry (slots with no sorted entry keep
 * it).  One work-item per tile walks its sorted entries. */
#define ENTRY_AHEAD 16   /* entries between a prefetch and its use in rasterize_bwd_entry_of */
__kernel void rasterize_bwd_entry_of(__global const int *sorted_values, /* [M] */
                                     __global const int2 *tile_ranges,  /* [n_tiles] */
                                     const int n_tiles, const int tiles_x,
                                     __global const int4 *rect,         /* [N] binning rects */
                                     __global const int *offsets,       /* [N + 1] binning offsets */
                                     __global int *entry_of)            /* [M] */
{
    const int t = get_global_id(0);
    if (t >= n_tiles) return;
    const int tx = t % tiles_x, ty = t / tiles_x;
    const int2 range = tile_ranges[t];
    for (int k = range.x; k < range.y; k++) {
#if HAVE_PREFETCH
        if (k + ENTRY_AHEAD < range.y) {   /* a later entry's Gaussian: its rect and offsets in flight */
            const int ga = sorted_values[k + ENTRY_AHEAD];
            PREFETCH(rect + ga);
            PREFETCH(offsets + ga);
        }
#endif
        const int u = binned_slot(rect, offsets, sorted_values[k], tx, ty);
        if (u >= 0) entry_of[u] = k;
    }
}

/* Deterministic mode, second pass: one work-item per Gaussian g sums the per-entry terms the
 * backward pass stored for its entries (v_entry in sorted order), taken in g's binning order
 * offsets[g] .. offsets[g + 1] (its rect's tiles row-major, entry_of[u] the sorted entry of slot
 * u), and writes its gradients.  v_entry is zero where the backward pass had nothing for an entry.
 * The arrays hold m_cap entries (the binning's capacity, ops/binning.py): slots at or past it exist
 * only in a list that overflowed (it has no tile ranges, so nothing was stored) and are not read. */
#define GATHER_AHEAD 32  /* slots between a prefetch and its use in rasterize_bwd_gather */
__kernel void rasterize_bwd_gather(__global const float *v_entry,   /* [m_cap, NV] in sorted order */
                                   __global const int *entry_of,     /* [m_cap] sorted entry of each slot */
                                   __global const int *offsets,      /* [N + 1] */
                                   const int n,
                                   const int m_cap,
                                   __global float *v_means2d,        /* [N, 2] */
                                   __global float *v_conic,          /* [N, 3] */
                                   __global float *v_opac,           /* [N] */
                                   __global float *v_features)       /* [N, C] */
{
    const int g = get_global_id(0);
    if (g >= n) return;
    float sum[NV];
    for (int k = 0; k < NV; k++) sum[k] = 0.0f;
    const int end = min(offsets[g + 1], m_cap);
#if HAVE_PREFETCH
    const int m_slots = min(offsets[n], m_cap);
#endif
    for (int u = offsets[g]; u < end; u++) {
#if HAVE_PREFETCH
        /* the rows a few slots ahead (the next Gaussians' slots follow): random reads in flight */
        if (u + GATHER_AHEAD < m_slots) {
            const int ea = entry_of[u + GATHER_AHEAD];
            if (ea >= 0) {
                PREFETCH(v_entry + ea * NV);
                PREFETCH(v_entry + ea * NV + NV - 1);
            }
        }
#endif
        const int e = entry_of[u];
        if (e < 0) continue;
        for (int k = 0; k < NV; k++) sum[k] += v_entry[e * NV + k];
    }
    v_means2d[2 * g] = sum[0];
    v_means2d[2 * g + 1] = sum[1];
    for (int k = 0; k < 3; k++) v_conic[3 * g + k] = sum[2 + k];
    v_opac[g] = sum[5];
    for (int c = 0; c < C; c++) v_features[g * C + c] = sum[6 + c];
}
