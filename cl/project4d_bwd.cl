/* project4d adjoint: one work-item per Gaussian (scalar variant) or W per work-item in lanes
 * (vector variant, -DP4_VW=W; project4d_common.h); recomputes the forward's geometry (p4_forward),
 * takes the colour's per-frequency SH sums from the forward (color_inner: the SH coefficients,
 * (NT+1) * SH_K * 3 floats per Gaussian, are not read again) and runs the chain rule back to the
 * parameters.  No atomics: every Gaussian writes only its own rows.  -DP4_SH_FACTORS: v_sh is
 * stored as its per-Gaussian factors (cl/sh_grad.h), 22 floats instead of 144 at degree 3, NT 2.
 * Reference adjoint: torch autograd of endowave_cl/reference/project.py::project4d_ref.
 * Notation: v_x = dL/dx.  2x2 / 3x3 / 4x4 matrices are row-major. */
#define P4_FORWARD_NO_RECT
#include "project4d_common.h"

/* d/dq of a matrix that is linear in q: v_q[k] = <v_M, M(e_k)> (Frobenius), for M_left or M_right
 * (quat_left_matrix / quat_right_matrix written out; same summation order as the j loop) */
P4_FN void v_quat_from_matrix(const p4f *vM, int left, p4f *vq) {
    vq[0] = vM[0] + vM[5] + vM[10] + vM[15];
    if (left) {
        vq[1] = -vM[1] + vM[4] - vM[11] + vM[14];
        vq[2] = -vM[2] + vM[7] + vM[8] - vM[13];
        vq[3] = -vM[3] - vM[6] + vM[9] + vM[12];
    } else {
        vq[1] = -vM[1] + vM[4] + vM[11] - vM[14];
        vq[2] = -vM[2] - vM[7] + vM[8] + vM[13];
        vq[3] = -vM[3] + vM[6] - vM[9] + vM[12];
    }
}

/* u = q / |q|:  v_q = (v_u - u (u . v_u)) / |q|  (the radial part of v_u is lost) */
P4_FN void v_quat_normalize(const p4f *u, p4f norm, const p4f *vu, p4f *vq) {
    p4f d = u[0] * vu[0] + u[1] * vu[1] + u[2] * vu[2] + u[3] * vu[3];
    for (int k = 0; k < 4; ++k) vq[k] = (vu[k] - u[k] * d) / norm;
}

__kernel void project4d_bwd(
    const int n,
    __global const float *means,     /* [N, 4] */
    __global const float *scales,    /* [N, 4] */
    __global const float *quat_l,    /* [N, 4] */
    __global const float *quat_r,    /* [N, 4] */
    __global const float *opacity,   /* [N] */
    __global const float *color_inner, /* [N, NT+1, 3] forward output: sum_k c[n, k, rgb] Y_k */
    __global const float *phase,     /* [N, NT+1] */
    P4_VIEW_ARGS,
    __global const int *radius,      /* [N] forward output: 0 = culled */
    __global const float *v_means2d, /* [N, 2] */
    __global const float *v_conic,   /* [N, 3] */
    __global const float *v_opac,    /* [N] */
    __global const float *v_features,/* [N, CHANNELS] */
    __global float *v_means,         /* [N, 4] */
    __global float *v_scales,        /* [N, 4] */
    __global float *v_quat_l,        /* [N, 4] */
    __global float *v_quat_r,        /* [N, 4] */
    __global float *v_opacity,       /* [N] */
    __global float *v_sh,            /* [N, NT+1, SH_K, 3]; with P4_SH_FACTORS its factors [N, SHF_SIZE] */
    __global float *v_phase)         /* [N, NT+1] */
{
    P4_INDEX_OR_RETURN(ix, n);
    P4Cam cam = p4_load_camera(cam_buf);
    P4State s;
    const p4i vis = p4_ldi(radius, 1, 0, ix) > 0;   /* culled by the forward: skip the recomputation */
    s.valid = vis;
    if (P4_ANY(vis)) {
        p4_forward(&cam, means, scales, quat_l, quat_r, ix, t, tiles_x, tiles_y, &s);
        s.valid = s.valid & vis;
    }
    const p4i ok = s.valid;   /* (vector: culled lanes store 0 through P4_SEL from here on) */
    const int nsh = SH_NCOEF;
    if (!P4_ANY(ok)) {
        const p4f zf = 0.0f;
        for (int k = 0; k < 4; ++k) {
            p4_st(v_means, 4, k, ix, zf); p4_st(v_scales, 4, k, ix, zf);
            p4_st(v_quat_l, 4, k, ix, zf); p4_st(v_quat_r, 4, k, ix, zf);
        }
        p4_st(v_opacity, 1, 0, ix, zf);
#ifdef P4_SH_FACTORS
        for (int k = 0; k < SHF_SIZE; ++k) p4_st(v_sh, SHF_SIZE, k, ix, zf);
#else
        for (int k = 0; k < nsh; ++k) p4_st(v_sh, nsh, k, ix, zf);
#endif
        for (int f = 0; f <= NT; ++f) p4_st(v_phase, NT + 1, f, ix, zf);
        return;
    }
    p4f vf[6];
    for (int c = 0; c < 6; ++c) vf[c] = (c < CHANNELS) ? p4_ld(v_features, CHANNELS, c, ix) : (p4f)(0.0f);

    /* ---- TEASH colour (the view direction is not differentiated) ---- */
    p4f d[3], Y[SH_K], cs[NT + 1], sn[NT + 1];
    p4_view_dir(&cam, &s, d);
    sh_basis(d, Y);
    teash_cos_sin(phase, ix, t, cs, sn);
    p4f inner[(NT + 1) * 3];   /* sum_k c[f, k, rgb] Y_k, stored by the forward (same bits) */
    for (int j = 0; j < (NT + 1) * 3; ++j) inner[j] = p4_ld(color_inner, (NT + 1) * 3, j, ix);
    p4f gcol[3];
    for (int c = 0; c < 3; ++c) {
        p4f acc = 0.0f;
        for (int f = 0; f <= NT; ++f) acc += inner[3 * f + c] * cs[f];
        gcol[c] = (0.5f + acc > 0.0f) ? vf[c] : (p4f)(0.0f);   /* max(0, .) passes the gradient where > 0 */
    }
#ifdef P4_SH_FACTORS
    /* v_sh as its factors (sh_grad.h), zero in culled lanes; Adam forms the products (sh_grad_expand) */
    for (int f = 0; f <= NT; ++f) p4_st(v_sh, SHF_SIZE, SHF_COS + f, ix, P4_SEL(ok, cs[f]));
    for (int c = 0; c < 3; ++c) p4_st(v_sh, SHF_SIZE, SHF_GCOL + c, ix, P4_SEL(ok, gcol[c]));
    for (int k = 0; k < SH_K; ++k) p4_st(v_sh, SHF_SIZE, SHF_Y + k, ix, P4_SEL(ok, Y[k]));
#else
    /* the products of sh_grad_expand (sh_grad.h) in the same order: both paths give the same bits */
    p4f gY[SH_K * 3];   /* gcol_c Y_k, shared by every frequency */
    for (int k = 0; k < SH_K; ++k)
        for (int c = 0; c < 3; ++c) gY[3 * k + c] = gcol[c] * Y[k];
#ifdef P4_VW
    /* v_sh (e = f SH_K 3 + j): whole blocks of VW transposed into rows (p4_st_rows), the rest scattered */
    p4f vshv[P4_NSH_ARR];
#pragma unroll
    for (int e = 0; e < nsh - nsh % VW; ++e) vshv[e] = P4_SEL(ok, gY[e % (SH_K * 3)] * cs[e / (SH_K * 3)]);
    p4_st_rows(v_sh, nsh, ix, vshv);
    for (int e = nsh - nsh % VW; e < nsh; ++e)
        p4_st(v_sh, nsh, e, ix, P4_SEL(ok, gY[e % (SH_K * 3)] * cs[e / (SH_K * 3)]));
#else
    for (int f = 0; f <= NT; ++f)
        for (int j = 0; j < SH_K * 3; ++j) p4_st(v_sh, nsh, f * SH_K * 3 + j, ix, gY[j] * cs[f]);
#endif
#endif   /* P4_SH_FACTORS */
    p4_st(v_phase, NT + 1, 0, ix, (p4f)(0.0f));          /* phi_0 is unused */
    /* dL/d cos(omega_f t + phi_f) = sum_c gcol_c inner_fc;  d cos(a)/d phi = -sin(a) */
    for (int f = 1; f <= NT; ++f)
        p4_st(v_phase, NT + 1, f, ix, P4_SEL(ok, -sn[f] * (gcol[0] * inner[3 * f] + gcol[1] * inner[3 * f + 1]
                                                           + gcol[2] * inner[3 * f + 2])));

    /* ---- opacity: opac = sigmoid(o) m ---- */
    p4f sig = 1.0f / (1.0f + P4_EXP(-p4_ld(opacity, 1, 0, ix)));
    p4f vo = p4_ld(v_opac, 1, 0, ix);
    p4_st(v_opacity, 1, 0, ix, P4_SEL(ok, vo * s.m * sig * (1.0f - sig)));
    p4f v_m = vo * sig;

    /* ---- means2d, depth channel and flow ---- */
    p4f x = s.p[0], y = s.p[1], z = s.p[2];
    p4f iz = 1.0f / z, iz2 = iz * iz;
    p4f vu0 = p4_ld(v_means2d, 2, 0, ix), vu1 = p4_ld(v_means2d, 2, 1, ix);  /* total gradient on proj(p) */
    p4f vp2[3] = {0.0f, 0.0f, 0.0f};
    if (has_flow) {
        p4f p2[3];
        p4_flow_point(&cam, means, ix, &s, t_flow, p2);
        p4f flow[2];
        const p4i fok = p4_flow(&cam, p2, s.means2d, tiles_x, tiles_y, flow);   /* else flow 0, no gradient */
        /* flow = proj(p2) - proj(p): -v_flow onto proj(p), J(p2)^T v_flow onto p2 */
        const p4f vfx = P4_WHERE(fok, vf[4]), vfy = P4_WHERE(fok, vf[5]);
        vu0 -= vfx; vu1 -= vfy;
        const p4f jz = 1.0f / p2[2];
        vp2[0] = P4_WHERE(fok, cam.fx * jz * vfx);
        vp2[1] = P4_WHERE(fok, cam.fy * jz * vfy);
        vp2[2] = P4_WHERE(fok, -cam.fx * p2[0] * jz * jz * vfx - cam.fy * p2[1] * jz * jz * vfy);
    }
    /* proj(p) = (fx x/z + cx, fy y/z + cy): its Jacobian is the EWA J */
    p4f vp[3];
    vp[0] = cam.fx * iz * vu0;
    vp[1] = cam.fy * iz * vu1;
    vp[2] = -cam.fx * x * iz2 * vu0 - cam.fy * y * iz2 * vu1 + vf[3];  /* + depth channel z */

    /* ---- conic = inverse(cov2d):  v_A = -Q G Q, G the symmetric gradient matrix of Q whose
     * off-diagonal entries each take half of v_conic[1] (Q01 = Q10 is stored once) ---- */
    p4f q0 = s.conic[0], q1 = s.conic[1], q2 = s.conic[2];
    p4f g0 = p4_ld(v_conic, 3, 0, ix), g1 = 0.5f * p4_ld(v_conic, 3, 1, ix), g2 = p4_ld(v_conic, 3, 2, ix);
    p4f qg00 = q0 * g0 + q1 * g1, qg01 = q0 * g1 + q1 * g2;  /* Q G */
    p4f qg10 = q1 * g0 + q2 * g1, qg11 = q1 * g1 + q2 * g2;
    p4f vA[4];                                               /* v_cov2d, symmetric [2, 2] */
    vA[0] = -(qg00 * q0 + qg01 * q1);
    vA[1] = -(qg00 * q1 + qg01 * q2);
    vA[2] = -(qg10 * q0 + qg11 * q1);
    vA[3] = -(qg10 * q1 + qg11 * q2);
    /* the +0.3 low-pass is additive: v_A passes unchanged to T cov T^T.
     * cov2d = T C T^T:  v_C = T^T v_A T,  v_T = 2 v_A T C  (v_A, C symmetric) */
    p4f vC[9];
    for (int r = 0; r < 3; ++r)
        for (int j = 0; j < 3; ++j) {
            p4f acc = 0.0f;
            for (int a = 0; a < 2; ++a)
                for (int b = 0; b < 2; ++b) acc += s.T[3 * a + r] * vA[2 * a + b] * s.T[3 * b + j];
            vC[3 * r + j] = acc;
        }
    p4f TC[6];
    for (int a = 0; a < 2; ++a)
        for (int j = 0; j < 3; ++j)
            TC[3 * a + j] = s.T[3 * a] * s.cov[j] + s.T[3 * a + 1] * s.cov[3 + j] + s.T[3 * a + 2] * s.cov[6 + j];
    p4f vT[6];
    for (int a = 0; a < 2; ++a)
        for (int j = 0; j < 3; ++j) vT[3 * a + j] = 2.0f * (vA[2 * a] * TC[j] + vA[2 * a + 1] * TC[3 + j]);
    /* T = J W:  v_J = v_T W^T; only J00, J02, J11, J12 are non-zero functions of p */
    p4f vJ00 = 0.0f, vJ02 = 0.0f, vJ11 = 0.0f, vJ12 = 0.0f;
    for (int j = 0; j < 3; ++j) {
        vJ00 += vT[j] * cam.R[j];
        vJ02 += vT[j] * cam.R[6 + j];
        vJ11 += vT[3 + j] * cam.R[3 + j];
        vJ12 += vT[3 + j] * cam.R[6 + j];
    }
    /* J00 = fx/z, J02 = -fx x/z^2, J11 = fy/z, J12 = -fy y/z^2 (J depends on the mean: no clamp) */
    vp[0] += vJ02 * (-cam.fx * iz2);
    vp[1] += vJ12 * (-cam.fy * iz2);
    vp[2] += -vJ00 * cam.fx * iz2 - vJ11 * cam.fy * iz2
             + 2.0f * vJ02 * cam.fx * x * iz2 * iz + 2.0f * vJ12 * cam.fy * y * iz2 * iz;

    /* ---- p = W mu + t_view:  v_mu = W^T v_p (same for p2 / mu2) ---- */
    p4f vmu[3], vmu2[3];
    for (int r = 0; r < 3; ++r) {
        vmu[r] = cam.R[r] * vp[0] + cam.R[3 + r] * vp[1] + cam.R[6 + r] * vp[2];
        vmu2[r] = cam.R[r] * vp2[0] + cam.R[3 + r] * vp2[1] + cam.R[6 + r] * vp2[2];
    }

    /* ---- conditional: mu = mu_x + sxt k, k = dt/stt; mu2 = mu_x + sxt k2, k2 = dt2/stt;
     * cov = Sxx - sxt sxt^T / stt;  m = exp(-dt^2 / (2 stt)) ---- */
    p4f k2 = 0.0f;
    if (has_flow) k2 = (t_flow - s.mean[3]) / s.stt;
    p4f v_sxt[3], w[3];
    p4f v_k = 0.0f, v_k2 = 0.0f;
    for (int r = 0; r < 3; ++r) {
        w[r] = s.sxt[r] / s.stt;                                    /* the velocity Sigma_xt / Sigma_tt */
        v_k += vmu[r] * s.sxt[r];
        v_k2 += vmu2[r] * s.sxt[r];
    }
    p4f wCw = 0.0f;
    for (int r = 0; r < 3; ++r) {
        p4f Cw = vC[3 * r] * w[0] + vC[3 * r + 1] * w[1] + vC[3 * r + 2] * w[2];
        v_sxt[r] = vmu[r] * s.k + vmu2[r] * k2 - 2.0f * Cw;       /* d(sxt sxt^T/stt) = 2 (v_C w) */
        wCw += w[r] * Cw;
    }
    /* stt enters k, k2 (d(dt/stt)/dstt = -k/stt), the cov (+ w^T v_C w) and m (m dt^2/(2 stt^2)) */
    p4f v_stt = -(v_k * s.k + v_k2 * k2) / s.stt + wCw + 0.5f * v_m * s.m * s.k * s.k;
    /* mu_t enters dt and dt2 (both with sign -): k, k2 and the marginal (dm/ddt = -m k) */
    p4f v_dt = v_k / s.stt - v_m * s.m * s.k;
    p4f v_dt2 = v_k2 / s.stt;
    for (int r = 0; r < 3; ++r) p4_st(v_means, 4, r, ix, P4_SEL(ok, vmu[r] + vmu2[r]));
    p4_st(v_means, 4, 3, ix, P4_SEL(ok, -(v_dt + v_dt2)));

    /* ---- Sigma = M M^T with M = R diag(S):  v_M = 2 V M, V the symmetric gradient of Sigma
     * (off-diagonal Sigma_xt read once: half of it on each side) ---- */
    p4f V[16];
    for (int r = 0; r < 3; ++r) {
        for (int j = 0; j < 3; ++j) V[4 * r + j] = vC[3 * r + j];   /* cov = Sxx - ...: v_Sxx = v_C */
        V[4 * r + 3] = 0.5f * v_sxt[r];
        V[12 + r] = 0.5f * v_sxt[r];
    }
    V[15] = v_stt;
    p4f vR[16];
    for (int r = 0; r < 4; ++r) {
        for (int j = 0; j < 4; ++j) {
            p4f acc = 0.0f;
            for (int k = 0; k < 4; ++k) acc += V[4 * r + k] * s.M[4 * k + j];
            vR[4 * r + j] = 2.0f * acc * s.S[j];   /* v_M = 2 V M; M = R S: v_R = v_M S */
        }
    }
    for (int j = 0; j < 4; ++j) {
        p4f acc = 0.0f;   /* v_S_j = sum_r v_M[r][j] R[r][j] = sum_r v_R[r][j] R[r][j] / S_j */
        for (int r = 0; r < 4; ++r) acc += vR[4 * r + j] * s.R[4 * r + j];
        p4_st(v_scales, 4, j, ix, P4_SEL(ok, acc));   /* S = exp(scales): v_scales = v_S S = the sum above */
    }
    /* R = M_l M_r:  v_Ml = v_R M_r^T,  v_Mr = M_l^T v_R */
    p4f vMl[16], vMr[16];
    for (int r = 0; r < 4; ++r)
        for (int j = 0; j < 4; ++j) {
            p4f al = 0.0f, ar = 0.0f;
            for (int k = 0; k < 4; ++k) {
                al += vR[4 * r + k] * s.Mr[4 * j + k];
                ar += s.Ml[4 * k + r] * vR[4 * k + j];
            }
            vMl[4 * r + j] = al;
            vMr[4 * r + j] = ar;
        }
    p4f vu[4], vq[4];
    v_quat_from_matrix(vMl, 1, vu);
    v_quat_normalize(s.qln, s.ql_norm, vu, vq);
    for (int k = 0; k < 4; ++k) p4_st(v_quat_l, 4, k, ix, P4_SEL(ok, vq[k]));
    v_quat_from_matrix(vMr, 0, vu);
    v_quat_normalize(s.qrn, s.qr_norm, vu, vq);
    for (int k = 0; k < 4; ++k) p4_st(v_quat_r, 4, k, ix, P4_SEL(ok, vq[k]));
}
