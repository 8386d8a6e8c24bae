/* select: the rows of the Gaussians alive at time t, and their parameters gathered into compact
 * arrays (docs/ARCHITECTURE.md "select"; host op endowave_cl/ops/select.py; reference
 * endowave_cl/reference/select.py).  OpenCL C 1.2.
 *
 * A 4D Gaussian's marginal weight at t is m = exp(-(t - mu_t)^2 / (2 Sigma_tt)); project4d culls it
 * when m < MARGINAL_CULL or Sigma_tt <= SIGMA_TT_MIN.  live_flags marks a superset of the rows that
 * pass that test: m >= MARGINAL_CULL * LIVE_SLACK (LIVE_SLACK just below 1, so that the rounding of
 * this shorter computation never drops a row project4d would keep) and Sigma_tt > SIGMA_TT_MIN / 2.
 * The rest contribute nothing at t, whatever their spatial parameters.
 *
 * Sigma_tt = sum_j (R[3, j] S_j)^2 with R = L(q_l) R(q_r) / (|q_l| |q_r|) (project4d_common.h
 * quat_left_matrix / quat_right_matrix; |q|^2 clamped at QUAT_NORM2_MIN as there), S = exp(scales).
 * Only row 3 of R is needed: u_j = sum_k L[3, k] R[k, j], with L[3, :] = (d, -c, b, a) for
 * q_l = (a, b, c, d).  LIVE_SLACK (0.99, ops/select.py) enters through dt2_per_stt_max. */

#include "project4d_common.h"   /* MARGINAL_CULL, SIGMA_TT_MIN, QUAT_NORM2_MIN, the lanes, P4_EXP */

/* flags[i] = 1 when Gaussian i may be alive at t (see above), else 0.  Scalar variant: one
 * Gaussian per work-item; vector variant (-DP4_VW=W, as project4d): W per work-item, one per lane. */
__kernel void live_flags(const int n,
                         __global const float *means,     /* [N, 4] */
                         __global const float *scales,    /* [N, 4] log */
                         __global const float *quat_l,    /* [N, 4] */
                         __global const float *quat_r,    /* [N, 4] */
                         const float t,
                         const float dt2_per_stt_max,     /* -2 ln(MARGINAL_CULL LIVE_SLACK) */
                         __global int *flags)             /* [N] */
{
    P4_INDEX_OR_RETURN(ix, n);
    p4f a[4], q[4], s[4];
    p4_ld4(quat_l, ix, a);
    p4_ld4(quat_r, ix, q);
    p4_ld4(scales, ix, s);
    const p4f l0 = a[3], l1 = -a[2], l2 = a[1], l3 = a[0];   /* row 3 of L(q_l) */
    /* row 3 of L(q_l) R(q_r), unnormalised; R(q) rows: (p,-r1,-r2,-r3) (r1,p,r3,-r2) (r2,-r3,p,r1) (r3,r2,-r1,p) */
    const p4f u0 = l0 * q[0] + l1 * q[1] + l2 * q[2] + l3 * q[3];
    const p4f u1 = -l0 * q[1] + l1 * q[0] - l2 * q[3] + l3 * q[2];
    const p4f u2 = -l0 * q[2] + l1 * q[3] + l2 * q[0] - l3 * q[1];
    const p4f u3 = -l0 * q[3] - l1 * q[2] + l2 * q[1] + l3 * q[0];
    const p4f nl = P4_FMAX(a[0] * a[0] + a[1] * a[1] + a[2] * a[2] + a[3] * a[3], (p4f)(QUAT_NORM2_MIN));
    const p4f nr = P4_FMAX(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3], (p4f)(QUAT_NORM2_MIN));
    const p4f stt = (u0 * u0 * P4_EXP(2.0f * s[0]) + u1 * u1 * P4_EXP(2.0f * s[1])
                     + u2 * u2 * P4_EXP(2.0f * s[2]) + u3 * u3 * P4_EXP(2.0f * s[3])) / (nl * nr);
    const p4f dt = t - p4_ld(means, 4, 3, ix);
    /* NaN fails both tests */
#ifdef P4_VW
    const p4i m = (stt > 0.5f * SIGMA_TT_MIN) & (dt * dt <= dt2_per_stt_max * stt);   /* lanes -1 / 0 */
    __global int *f = flags + ix.base;
#define FLAG_LANE(l, s) if (l >= ix.lo) f[l] = m.s != 0;
    P4_STMTS(FLAG_LANE)
#undef FLAG_LANE
#else
    flags[ix] = (stt > 0.5f * SIGMA_TT_MIN) && (dt * dt <= dt2_per_stt_max * stt);
#endif
}

/* rows[offsets[i]] = i for every flagged i whose slot is below cap (offsets [N + 1]: the exclusive
 * scan of flags, offsets[N] = L the selected count), and rows[j] = -1 for L <= j < cap: a buffer of
 * cap rows (cap <= N) sized before L is known holds the first min(L, cap) selected rows, then
 * padding; L > cap (an overflow) is detected on the host from L. */
__kernel void live_rows(const int n, __global const int *flags, __global const int *offsets,
                        const int cap, __global int *rows)   /* [cap] */
{
    const int i = get_global_id(0);
    if (i >= n) return;
    if (i < cap && i >= offsets[n]) rows[i] = -1;
    if (flags[i] && offsets[i] < cap) rows[offsets[i]] = i;
}

#ifdef SH_W
/* The parameters of the selected rows: row r of each output is row rows[r] of its input (one
 * work-item per selected row); a padding row (rows[r] < 0) gets a Gaussian that project4d culls at
 * every time of the sequence (centred at DEAD_T, unit scales, identity rotations, opacity logit
 * DEAD_OPACITY, no colour), so that every later stage treats it as it treats any culled row.
 * -DSH_W, -DPHASE_W: floats per row of sh and phase; -DDEAD_T, -DDEAD_OPACITY (ops/select.py). */
__kernel void gather_params(const int n_rows, __global const int *rows,
                            __global const float4 *means, __global const float4 *scales,
                            __global const float4 *quat_l, __global const float4 *quat_r,
                            __global const float *opacity, __global const float *sh,
                            __global const float *phase,
                            __global float4 *o_means, __global float4 *o_scales,
                            __global float4 *o_quat_l, __global float4 *o_quat_r,
                            __global float *o_opacity, __global float *o_sh, __global float *o_phase)
{
    const int r = get_global_id(0);
    if (r >= n_rows) return;
#if HAVE_PREFETCH && ROWS_AHEAD > 0
    /* the row ROWS_AHEAD work-items on, requested while this one is copied (the selected rows are
     * scattered, so the hardware's stream prefetch misses them) */
    if (r + ROWS_AHEAD < n_rows) {
        const int a = max(rows[r + ROWS_AHEAD], 0);   /* padding (-1): row 0, a harmless request */
        PREFETCH(means + a); PREFETCH(scales + a); PREFETCH(quat_l + a); PREFETCH(quat_r + a);
        PREFETCH(opacity + a);
        prefetch_floats(sh + a * SH_W, SH_W);
        prefetch_floats(phase + a * PHASE_W, PHASE_W);
    }
#endif
    const int i = rows[r];
    if (i < 0) {
        o_means[r] = (float4)(0.0f, 0.0f, 0.0f, DEAD_T);
        o_scales[r] = (float4)(0.0f);
        o_quat_l[r] = (float4)(1.0f, 0.0f, 0.0f, 0.0f);
        o_quat_r[r] = (float4)(1.0f, 0.0f, 0.0f, 0.0f);
        o_opacity[r] = DEAD_OPACITY;
        for (int c = 0; c < SH_W; ++c) o_sh[r * SH_W + c] = 0.0f;
        for (int c = 0; c < PHASE_W; ++c) o_phase[r * PHASE_W + c] = 0.0f;
        return;
    }
    o_means[r] = means[i];
    o_scales[r] = scales[i];
    o_quat_l[r] = quat_l[i];
    o_quat_r[r] = quat_r[i];
    o_opacity[r] = opacity[i];
#if SH_W % 4 == 0   /* rows of whole float4s, each 16-byte aligned */
    __global const float4 *src4 = (__global const float4 *)sh + i * (SH_W / 4);
    __global float4 *dst4 = (__global float4 *)o_sh + r * (SH_W / 4);
    for (int c = 0; c < SH_W / 4; ++c) dst4[c] = src4[c];
#else
    for (int c = 0; c < SH_W; ++c) o_sh[r * SH_W + c] = sh[i * SH_W + c];
#endif
    for (int c = 0; c < PHASE_W; ++c) o_phase[r * PHASE_W + c] = phase[i * PHASE_W + c];
}
#endif
