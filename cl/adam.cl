/* Adam on the device: one launch updates every parameter group.
 *
 * A work-item updates a run of ADAM_RUN consecutive elements of one group, as 8-wide vectors (a
 * group's last, shorter run element by element).  The global id runs over the concatenation of the
 * groups' runs: [0, r0) are group 0's ceil(n0 / ADAM_RUN) runs, [r0, r0 + r1) group 1's, ... (host
 * order: means, scales, quat_l, quat_r, opacity, sh, phase; see endowave_cl/ops/adam.py).
 * -DADAM_SH_FACTORS: the sh group's gradient comes as per-Gaussian factors (adam_sh_row below).
 *
 * Per-element learning rate inside a group: an element at column c = j % row_len
 * of its row uses lr_a when c < split, else lr_b.  This gives
 *   means:  row_len 4, split 3  -> x, y, z at the (decayed) position lr, t at lr_b;
 *   sh:     row_len (NT+1)*K*3, split 3 -> the DC term of n = 0 at lr_a, the rest lr_b;
 *   others: split = row_len (one lr).
 * An element whose lr is 0 is frozen: neither the parameter nor its moments change.
 * With skip_culled, so is every element of a Gaussian whose visible[g] is 0 (the step's projected
 * radius: culled at this step's time, so its gradient is 0): its parameters and moments keep their
 * values instead of decaying the moments and moving on momentum (gsplat's SelectiveAdam).  The
 * bias correction still counts every step.
 * gated: the whole update is left out where skip[0] != 0 (cl/util.cl step_gate: a step whose
 * outcome the host reads later, found non-finite or overflowed on the device); the host then
 * does not count the step either (ops/adam.py DeviceAdam.step(skip=...)).
 *
 * adam_step_rows (below) updates only the rows a step selected (ops/select.py), their gradients
 * given as compact arrays.
 *
 * Bias-corrected Adam exactly as torch.optim.Adam (no weight decay, no amsgrad):
 *   m = b1 m + (1 - b1) g;  v = b2 v + (1 - b2) g^2
 *   p -= (lr / bc1) * m / (sqrt(v) / sqrt(bc2) + eps),  bc1 = 1 - b1^t, bc2 = 1 - b2^t
 * The host passes omb1 = 1 - b1 and omb2 = 1 - b2 (rounded from double, as torch does:
 * 1.0f - 0.999f is 1.3e-5 off), inv_bc1 = 1 / bc1 and inv_sqrt_bc2 = 1 / sqrt(bc2).
 */
#include "common.h"

#define GROUP_ARGS(k)                                                                   \
    __global float *p##k, __global const float *g##k, __global float *m##k,             \
    __global float *v##k, const int n##k, const int row##k, const int split##k,         \
    const float lra##k, const float lrb##k

#define ADAM_RUN 8   /* elements per work-item (float8) */

#define GROUP_DISPATCH(k)                                                               \
    if (i < (n##k + ADAM_RUN - 1) / ADAM_RUN) {                                         \
        adam_run(p##k, g##k, m##k, v##k, n##k, i * ADAM_RUN, row##k, split##k, lra##k,  \
                 lrb##k, beta1, beta2, omb1, omb2, eps, inv_bc1, inv_sqrt_bc2, vis);    \
        return;                                                                         \
    }                                                                                   \
    i -= (n##k + ADAM_RUN - 1) / ADAM_RUN;

inline void adam_element(__global float *p, const float gj, __global float *m, __global float *v,
                         const int j, const float lr, const float beta1, const float beta2,
                         const float omb1, const float omb2, const float eps, const float inv_bc1,
                         const float inv_sqrt_bc2) {
    if (lr == 0.0f) return;
    const float mj = beta1 * m[j] + omb1 * gj;
    const float vj = beta2 * v[j] + omb2 * gj * gj;
    m[j] = mj;
    v[j] = vj;
    const float denom = sqrt1(vj) * inv_sqrt_bc2 + eps;
    p[j] -= (lr * inv_bc1) * mj / denom;
}

/* The same operations on W consecutive elements j0 .. j0 + W - 1 (W = 8: the runs of adam_run;
 * W = 4: adam_step_rows) with their gradients gj and learning rates lr; frozen lanes (lr 0) store
 * back their old values. */
#define ADAM_UPDATE_W(W)                                                                         \
inline void adam_update##W(__global float *p, const float##W gj, __global float *m,              \
                           __global float *v, const int j0, const float##W lr, const float beta1, \
                           const float beta2, const float omb1, const float omb2, const float eps, \
                           const float inv_bc1, const float inv_sqrt_bc2) {                      \
    const int##W frozen = lr == 0.0f;                                                           \
    const float##W m0 = load##W(m + j0), v0 = load##W(v + j0), p0 = load##W(p + j0);            \
    const float##W mj = beta1 * m0 + omb1 * gj;                                                 \
    const float##W vj = beta2 * v0 + omb2 * gj * gj;                                            \
    const float##W denom = sqrt##W(vj) * inv_sqrt_bc2 + eps;                                    \
    const float##W pj = p0 - (lr * inv_bc1) * mj / denom;                                       \
    store##W(m + j0, frozen ? m0 : mj);                                                         \
    store##W(v + j0, frozen ? v0 : vj);                                                         \
    store##W(p + j0, frozen ? p0 : pj);                                                         \
}
ADAM_UPDATE_W(8)
ADAM_UPDATE_W(4)

/* Elements j0 .. j0 + ADAM_RUN - 1 of a group of n (the group's last, shorter run element by
 * element); vis: the visibility array, or 0 (no skipping).  Element j belongs to Gaussian j / row. */
inline void adam_run(__global float *p, __global const float *g, __global float *m,
                     __global float *v, const int n, const int j0, const int row, const int split,
                     const float lra, const float lrb, const float beta1, const float beta2,
                     const float omb1, const float omb2, const float eps, const float inv_bc1,
                     const float inv_sqrt_bc2, __global const int *vis) {
    if (j0 + ADAM_RUN > n) {
        for (int j = j0; j < n; j++) {
            const float lr = (vis && vis[j / row] == 0) ? 0.0f : (((j % row) < split) ? lra : lrb);
            adam_element(p, g[j], m, v, j, lr, beta1, beta2, omb1, omb2, eps, inv_bc1, inv_sqrt_bc2);
        }
        return;
    }
    float lr_l[ADAM_RUN];
    int col = j0 % row, gi = j0 / row;
    for (int l = 0; l < ADAM_RUN; l++) {
        lr_l[l] = (vis && vis[gi] == 0) ? 0.0f : (col < split ? lra : lrb);
        if (++col == row) { col = 0; gi++; }
    }
    bool live = false;
    for (int l = 0; l < ADAM_RUN; l++) live |= lr_l[l] != 0.0f;
    if (!live) return;   /* all frozen: nothing to load or store */
    const float8 lr = (float8)(lr_l[0], lr_l[1], lr_l[2], lr_l[3], lr_l[4], lr_l[5], lr_l[6], lr_l[7]);
    adam_update8(p, load8(g + j0), m, v, j0, lr, beta1, beta2, omb1, omb2, eps, inv_bc1, inv_sqrt_bc2);
}

#ifdef ADAM_SH_FACTORS
#include "sh_grad.h"
/* The sh group with its gradient as factors (cl/sh_grad.h; -DADAM_SH_FACTORS with SH_DEGREE and NT):
 * work-item i takes Gaussian i's row of SH_NCOEF elements, forms their gradients from its SHF_SIZE
 * factors (the products project4d_bwd would have stored: the same bits) and updates the row in
 * runs of ADAM_RUN, the rest element by element, with the columns' learning rates as adam_run.
 * The group's global gradient array of SH_NCOEF floats per Gaussian is never written or read. */
inline void adam_sh_row(__global float *p, __global const float *fac, __global float *m,
                        __global float *v, const int i, const int split, const float lra,
                        const float lrb, const float beta1, const float beta2, const float omb1,
                        const float omb2, const float eps, const float inv_bc1,
                        const float inv_sqrt_bc2, __global const int *vis) {
    if (vis && vis[i] == 0) return;   /* culled: the whole row is frozen */
    float fr[SHF_SIZE], g[SH_NCOEF];
    for (int e = 0; e < SHF_SIZE; ++e) fr[e] = fac[SHF_SIZE * i + e];
    sh_grad_expand(fr, g);
    const int j0 = SH_NCOEF * i;
    int c = 0;
    for (; c + ADAM_RUN <= SH_NCOEF; c += ADAM_RUN) {
        float lr_l[ADAM_RUN];
        for (int l = 0; l < ADAM_RUN; l++) lr_l[l] = c + l < split ? lra : lrb;
        const float8 lr = (float8)(lr_l[0], lr_l[1], lr_l[2], lr_l[3], lr_l[4], lr_l[5], lr_l[6], lr_l[7]);
        const float8 gj = (float8)(g[c], g[c + 1], g[c + 2], g[c + 3], g[c + 4], g[c + 5], g[c + 6], g[c + 7]);
        adam_update8(p, gj, m, v, j0 + c, lr, beta1, beta2, omb1, omb2, eps, inv_bc1, inv_sqrt_bc2);
    }
    for (; c < SH_NCOEF; c++)
        adam_element(p, g[c], m, v, j0 + c, c < split ? lra : lrb, beta1, beta2, omb1, omb2, eps, inv_bc1,
                     inv_sqrt_bc2);
}

/* SH_GPW consecutive Gaussians per work-item, the fewest whose rows fill whole runs of ADAM_RUN
 * (SH_GPW * SH_NCOEF a multiple of 8: 2 at degree 1, where a row is 36 floats; 1 at degree 3), so
 * that the block is updated in aligned 8-wide runs with no element-by-element tail; degree 2 (81
 * floats, a block of 648) keeps one Gaussian per work-item.  Mirrored by ops/adam.py sh_gaussians_per_item. */
#define SH_GCD8 ((SH_NCOEF % 8 == 0) ? 8 : (SH_NCOEF % 4 == 0) ? 4 : (SH_NCOEF % 2 == 0) ? 2 : 1)
#define SH_GPW ((8 / SH_GCD8) * SH_NCOEF <= 128 ? 8 / SH_GCD8 : 1)
#define SH_BLOCK (SH_GPW * SH_NCOEF)

/* Gaussians SH_GPW i .. SH_GPW i + SH_GPW - 1 of the sh group (nrows Gaussians): when all of them
 * exist, their gradients from their factors (sh_grad_expand, the same products as adam_sh_row) and
 * the block in runs of ADAM_RUN, each lane with its column's lr, 0 for a culled Gaussian's lanes
 * (adam_update8 stores back their old values: the same result as leaving the row alone); the same
 * operations per element as adam_sh_row.  A short last block: adam_sh_row per Gaussian. */
inline void adam_sh_block(__global float *p, __global const float *fac, __global float *m,
                          __global float *v, const int nrows, const int i, const int split,
                          const float lra, const float lrb, const float beta1, const float beta2,
                          const float omb1, const float omb2, const float eps, const float inv_bc1,
                          const float inv_sqrt_bc2, __global const int *vis) {
    const int g0 = SH_GPW * i;
    if (SH_GPW == 1 || g0 + SH_GPW > nrows) {
        for (int q = g0; q < min(g0 + SH_GPW, nrows); q++)
            adam_sh_row(p, fac, m, v, q, split, lra, lrb, beta1, beta2, omb1, omb2, eps, inv_bc1,
                        inv_sqrt_bc2, vis);
        return;
    }
    int live[SH_GPW];
    bool any = false;
    for (int q = 0; q < SH_GPW; q++) {
        live[q] = !(vis && vis[g0 + q] == 0);
        any |= live[q] != 0;
    }
    if (!any) return;   /* every row culled: frozen */
    float g[SH_BLOCK];
    for (int q = 0; q < SH_GPW; q++) {
        float fr[SHF_SIZE];
        for (int e = 0; e < SHF_SIZE; ++e) fr[e] = live[q] ? fac[SHF_SIZE * (g0 + q) + e] : 0.0f;
        sh_grad_expand(fr, g + q * SH_NCOEF);
    }
    const int j0 = SH_NCOEF * g0;
    for (int c = 0; c < SH_BLOCK; c += ADAM_RUN) {
        float lr_l[ADAM_RUN];
        for (int l = 0; l < ADAM_RUN; l++) {
            const int col = (c + l) % SH_NCOEF;
            lr_l[l] = live[(c + l) / SH_NCOEF] ? (col < split ? lra : lrb) : 0.0f;
        }
        const float8 lr = (float8)(lr_l[0], lr_l[1], lr_l[2], lr_l[3], lr_l[4], lr_l[5], lr_l[6], lr_l[7]);
        const float8 gj = (float8)(g[c], g[c + 1], g[c + 2], g[c + 3], g[c + 4], g[c + 5], g[c + 6], g[c + 7]);
        adam_update8(p, gj, m, v, j0 + c, lr, beta1, beta2, omb1, omb2, eps, inv_bc1, inv_sqrt_bc2);
    }
}

/* group k given as factors: ceil(nrows / SH_GPW) work-items, SH_GPW Gaussians each */
#define GROUP_DISPATCH_SH_FACTORS(k)                                                    \
    if (i < (n##k / SH_NCOEF + SH_GPW - 1) / SH_GPW) {                                  \
        adam_sh_block(p##k, g##k, m##k, v##k, n##k / SH_NCOEF, i, split##k, lra##k,     \
                      lrb##k, beta1, beta2, omb1, omb2, eps, inv_bc1, inv_sqrt_bc2, vis); \
        return;                                                                         \
    }                                                                                   \
    i -= (n##k / SH_NCOEF + SH_GPW - 1) / SH_GPW;
#endif

__kernel void adam_step(GROUP_ARGS(0), GROUP_ARGS(1), GROUP_ARGS(2), GROUP_ARGS(3),
                        GROUP_ARGS(4), GROUP_ARGS(5), GROUP_ARGS(6),
                        const float beta1, const float beta2,
                        const float omb1, const float omb2, const float eps,
                        const float inv_bc1, const float inv_sqrt_bc2,
                        __global const int *visible,   /* [N] projected radius (0: culled) */
                        const int skip_culled,
                        __global const int *skip,      /* [1] the step gate (cl/util.cl step_gate) */
                        const int gated) {
    if (gated && skip[0] != 0) return;   /* a skipped step: nothing changes */
    int i = get_global_id(0);
    __global const int *vis = skip_culled ? visible : 0;
    GROUP_DISPATCH(0)
    GROUP_DISPATCH(1)
    GROUP_DISPATCH(2)
    GROUP_DISPATCH(3)
    GROUP_DISPATCH(4)
#ifdef ADAM_SH_FACTORS
    GROUP_DISPATCH_SH_FACTORS(5)   /* sh */
#else
    GROUP_DISPATCH(5)
#endif
    GROUP_DISPATCH(6)
    /* past the last group: a padding work-item, nothing to do */
}

/* ---- Adam on selected rows (ops/adam.py DeviceAdam.step(rows=...)) ---------------------------
 * The step ran on the parameters of the rows alive at its time, gathered into compact arrays
 * (ops/select.py): work-item i updates row rows[i] of every group from row i of the compact
 * gradients, in runs of 4 (adam_update4) and element by element after the last whole run (the
 * operations of adam_update8 lane by lane).
 * vis: the compact projected radius (0: the row is frozen, as skip_culled above).  row_k = 0: the
 * group has no gradient (all its lrs are 0) and is left alone. */
#define ROW_ARGS(k)                                                                     \
    __global float *p##k, __global const float *g##k, __global float *m##k,             \
    __global float *v##k, const int row##k, const int split##k, const float lra##k,     \
    const float lrb##k

#define LR4(c, split, lra, lrb)                                                         \
    (float4)((c) < (split) ? (lra) : (lrb), (c) + 1 < (split) ? (lra) : (lrb),         \
             (c) + 2 < (split) ? (lra) : (lrb), (c) + 3 < (split) ? (lra) : (lrb))

#define ROW_UPDATE(k)                                                                   \
    {                                                                                   \
        int c = 0;                                                                      \
        for (; c + 4 <= row##k; c += 4)                                                 \
            adam_update4(p##k, load4(g##k + i * row##k + c), m##k, v##k, r * row##k + c, \
                         LR4(c, split##k, lra##k, lrb##k), beta1, beta2, omb1, omb2, eps, \
                         inv_bc1, inv_sqrt_bc2);                                        \
        for (; c < row##k; ++c)                                                         \
            adam_element(p##k, g##k[i * row##k + c], m##k, v##k, r * row##k + c,        \
                         c < split##k ? lra##k : lrb##k, beta1, beta2, omb1, omb2, eps, \
                         inv_bc1, inv_sqrt_bc2);                                        \
    }

/* every line of row ra of group k's parameters and moments (row_k floats from ra row_k) */
#define PREFETCH_ROW(k)                                                                 \
    if (row##k > 0) {                                                                   \
        prefetch_floats(p##k + ra * row##k, row##k);                                    \
        prefetch_floats(m##k + ra * row##k, row##k);                                    \
        prefetch_floats(v##k + ra * row##k, row##k);                                    \
    }

__kernel void adam_step_rows(ROW_ARGS(0), ROW_ARGS(1), ROW_ARGS(2), ROW_ARGS(3),
                             ROW_ARGS(4), ROW_ARGS(5), ROW_ARGS(6),
                             const float beta1, const float beta2,
                             const float omb1, const float omb2, const float eps,
                             const float inv_bc1, const float inv_sqrt_bc2,
                             const int n_rows,
                             __global const int *rows,      /* [L] rows of the full arrays */
                             __global const int *visible,   /* [L] compact projected radius */
                             const int skip_culled,
                             __global const int *skip,      /* [1] the step gate (cl/util.cl step_gate) */
                             const int gated) {
    const int i = get_global_id(0);
    if (i >= n_rows) return;
    if (gated && skip[0] != 0) return;   /* a skipped step: nothing changes */
#if HAVE_PREFETCH && ROWS_AHEAD > 0
    /* the row ROWS_AHEAD work-items on: its lines in every array, requested while this row is
     * updated (the selected rows are scattered, so the hardware's stream prefetch misses them) */
    if (i + ROWS_AHEAD < n_rows) {
        const int ra = max(rows[i + ROWS_AHEAD], 0);   /* padding (-1): row 0, a harmless request */
        PREFETCH_ROW(0) PREFETCH_ROW(1) PREFETCH_ROW(2) PREFETCH_ROW(3) PREFETCH_ROW(4)
        PREFETCH_ROW(5) PREFETCH_ROW(6)
    }
#endif
    if (skip_culled && visible[i] == 0) return;
    const int r = rows[i];
    if (r < 0) return;   /* padding after the selected rows (ops/select.py) */
    ROW_UPDATE(0)
    ROW_UPDATE(1)
    ROW_UPDATE(2)
    ROW_UPDATE(3)
    ROW_UPDATE(4)
#ifdef ADAM_SH_FACTORS
    if (row5 > 0) {   /* sh: its gradient from row i's factors (adam_sh_row) */
        float fr[SHF_SIZE], gs[SH_NCOEF];
        for (int e = 0; e < SHF_SIZE; ++e) fr[e] = g5[SHF_SIZE * i + e];
        sh_grad_expand(fr, gs);
        int c = 0;
        for (; c + 4 <= SH_NCOEF; c += 4)
            adam_update4(p5, (float4)(gs[c], gs[c + 1], gs[c + 2], gs[c + 3]), m5, v5, r * SH_NCOEF + c,
                         LR4(c, split5, lra5, lrb5), beta1, beta2, omb1, omb2, eps, inv_bc1, inv_sqrt_bc2);
        for (; c < SH_NCOEF; ++c)
            adam_element(p5, gs[c], m5, v5, r * SH_NCOEF + c, c < split5 ? lra5 : lrb5, beta1, beta2,
                         omb1, omb2, eps, inv_bc1, inv_sqrt_bc2);
    }
#else
    ROW_UPDATE(5)
#endif
    ROW_UPDATE(6)
}
