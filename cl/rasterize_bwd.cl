/* Tile rasterizer, adjoint (docs/ARCHITECTURE.md "rasterize").  OpenCL C 1.2.
 *
 * Same work layout as rasterize.cl: one TILE x TILE work-group per tile, one pixel per work-item.
 * Each pixel walks its tile's list back to front, starting at its last contributor (last[p] - 1),
 * so batches are visited from the one holding the tile's largest `last` down to the first.
 *
 * Transmittance is recovered by division, as in 3DGS: starting from T = T_final, for each
 * contributor k (back to front) T_k = T_{k+1} / (1 - alpha_k); alpha_k <= ALPHA_MAX keeps the
 * divisor >= 1 - ALPHA_MAX.  The skip tests (power > 0, alpha < ALPHA_MIN) use the same arithmetic
 * as the forward kernel, so the same Gaussians are treated as contributors.
 *
 * With S_c = sum_{j behind k} f_jc alpha_j T_j (the colour composited behind k):
 *   d out_c / d alpha_k   = f_kc T_k - S_c / (1 - alpha_k)
 *   d alpha_pix / d alpha_k = T_final / (1 - alpha_k)            (alpha_pix = 1 - T_final)
 *   d out_c / d f_kc      = alpha_k T_k
 * and alpha_k = opac_k G_k (G_k = exp(power)) unless the ALPHA_MAX clamp is active, where the
 * gradient to opac and power is zero.
 *
 * Like the forward pass, a pixel walks only the list of its SUB x SUB sub-block (rasterize.cl).
 *
 * Reduction: per batch, every Gaussian of the batch has a slot of local accumulators; the 256
 * pixels add into it with local CAS adds (atomic_add_local_f); after a barrier, work-item l adds
 * slot l to the global gradients with one atomic_add_global_f per value.  Order of the float adds
 * is therefore not fixed: results vary in the last bits from run to run.
 *
 * Build options: -DC, -DALPHA_MAX, -DALPHA_MIN (set by endowave_cl/ops/rasterize.py).
 */
#include "common.h"
#define RASTERIZE_HELPERS_ONLY
#include "rasterize.cl"   /* gauss_power, exp_nonpos, skip_threshold, cull_box, build_sub_lists */

#define NV (6 + C)   /* accumulated values per Gaussian: mean (2), conic (3), opac (1), features (C) */
/* Gaussians per batch: half the forward's, so that the local arrays (about 19 KiB for C = 6) fit
 * the 32 KiB of the smallest devices we run on (Oclgrind). */
#define BATCH (TILE_PIXELS / 2)

__kernel __attribute__((reqd_work_group_size(TILE, TILE, 1)))
void rasterize_bwd(__global const float2 *means2d,   /* [N, 2] */
                   __global const float *conic,      /* [N, 3] */
                   __global const float *opac,       /* [N] */
                   __global const float *features,   /* [N, C] */
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
                   volatile __global float *v_features) /* [N, C] */
{
    __local float2 l_mean[BATCH];
    __local float4 l_cop[BATCH];                 /* (a, b, c, opac) */
    __local float l_feat[BATCH * C];
    __local int l_gid[BATCH];
    __local float l_thr[BATCH];
    __local float4 l_box[BATCH];
    __local uchar l_list[N_SUB * BATCH];
    __local int l_len[N_SUB];
    __local float l_acc[BATCH * NV];             /* [batch slot, NV] gradient accumulators */
    __local int l_max_last;

    const int lx = get_local_id(0), ly = get_local_id(1);
    const int lid = ly * TILE + lx;
    const int tx = get_group_id(0), ty = get_group_id(1);
    const int tile = ty * tiles_x + tx;
    const int ix = get_global_id(0), iy = get_global_id(1);
    const bool inside = ix < width && iy < height;
    const float px = (float)ix + 0.5f, py = (float)iy + 0.5f;
    const int p = iy * width + ix;
    const int my_sub = (ly / SUB) * SUBS_PER_ROW + lx / SUB;

    const int2 range = tile_ranges[tile];

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

    if (lid == 0) l_max_last = 0;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (last > 0) atomic_max(&l_max_last, last);
    barrier(CLK_LOCAL_MEM_FENCE);
    const int n_batches = (l_max_last + BATCH - 1) / BATCH;   /* uniform */

    for (int b = n_batches - 1; b >= 0; b--) {
        const int base = range.x + b * BATCH;
        const int count = min(BATCH, range.y - base);
        if (lid < count) {
            const int g = sorted_values[base + lid];
            l_gid[lid] = g;
            l_mean[lid] = means2d[g];
            l_cop[lid] = (float4)(conic[3 * g], conic[3 * g + 1], conic[3 * g + 2], opac[g]);
            for (int c = 0; c < C; c++) l_feat[lid * C + c] = features[g * C + c];
            const float thr = skip_threshold(l_cop[lid].w);
            l_thr[lid] = thr;
            l_box[lid] = cull_box(l_mean[lid], l_cop[lid], thr);
        }
        if (lid < BATCH)
            for (int k = 0; k < NV; k++) l_acc[lid * NV + k] = 0.0f;
        barrier(CLK_LOCAL_MEM_FENCE);
        build_sub_lists(lid, count, tx * TILE, ty * TILE, l_box, l_list, l_len, BATCH);
        barrier(CLK_LOCAL_MEM_FENCE);

        const int j_end = last - b * BATCH;   /* one past this pixel's last contributor here */
        __local const uchar *mine = l_list + my_sub * BATCH;
        for (int i = l_len[my_sub] - 1; i >= 0; i--) {
            const int j = mine[i];
            if (j >= j_end) continue;
            const float4 cop = l_cop[j];
            const float2 d = l_mean[j] - (float2)(px, py);
            const float power = gauss_power(cop, d);
            if (power > 0.0f || power < l_thr[j]) continue;
            const float G = exp_nonpos(power);
            const float raw = cop.w * G;
            const float alpha = raw < ALPHA_MAX ? raw : ALPHA_MAX;
            if (alpha < ALPHA_MIN) continue;
            const float one_m = 1.0f - alpha;
            T = T / one_m;                           /* transmittance in front of Gaussian j */
            const float w = alpha * T;
            float v_al = va * T_fin / one_m;         /* d L / d alpha_j */
            volatile __local float *acc = l_acc + j * NV;
            for (int c = 0; c < C; c++) {
                const float f = l_feat[j * C + c];
                v_al += vo[c] * (f * T - S[c] / one_m);
                S[c] += f * w;
                atomic_add_local_f(acc + 6 + c, vo[c] * w);
            }
            if (raw <= ALPHA_MAX) {                  /* the clamp blocks the gradient */
                const float v_power = v_al * alpha;
                atomic_add_local_f(acc + 0, -v_power * (cop.x * d.x + cop.y * d.y));
                atomic_add_local_f(acc + 1, -v_power * (cop.z * d.y + cop.y * d.x));
                atomic_add_local_f(acc + 2, -0.5f * v_power * d.x * d.x);
                atomic_add_local_f(acc + 3, -v_power * d.x * d.y);
                atomic_add_local_f(acc + 4, -0.5f * v_power * d.y * d.y);
                atomic_add_local_f(acc + 5, v_al * G);
            }
        }
        barrier(CLK_LOCAL_MEM_FENCE);

        if (lid < count) {
            const int g = l_gid[lid];
            __local const float *acc = l_acc + lid * NV;
            /* slots are read with plain loads: every CAS on them happened before the barrier */
            if (acc[0] != 0.0f) atomic_add_global_f(v_means2d + 2 * g, acc[0]);
            if (acc[1] != 0.0f) atomic_add_global_f(v_means2d + 2 * g + 1, acc[1]);
            for (int k = 0; k < 3; k++)
                if (acc[2 + k] != 0.0f) atomic_add_global_f(v_conic + 3 * g + k, acc[2 + k]);
            if (acc[5] != 0.0f) atomic_add_global_f(v_opac + g, acc[5]);
            for (int c = 0; c < C; c++)
                if (acc[6 + c] != 0.0f) atomic_add_global_f(v_features + g * C + c, acc[6 + c]);
        }
        barrier(CLK_LOCAL_MEM_FENCE);   /* the next batch overwrites the local arrays */
    }
}
