/* project4d forward (docs/ARCHITECTURE.md "project4d").  Scalar variant: one work-item per
 * Gaussian; vector variant (-DP4_VW=W): W Gaussians per work-item, one per lane (project4d_common.h).
 * Reference: endowave_cl/reference/project.py::project4d_ref.
 * Build option -DALPHA_MIN (layout.py): the tile rect covers only where alpha can reach it;
 * -DP4_NO_TIGHT_RECT keeps the 3-sigma rect (tests/kernels/test_tight_rect.py compares the two). */
#include "project4d_common.h"

#if defined(P4_VW) && HAVE_PREFETCH
/* Part `part` of P4_PF_PARTS of the next work-item's SH rows (VW rows of SH_NCOEF floats: most of
 * the bytes this kernel reads), asked for into L2 while this work-item computes its geometry: the
 * parts are spread over the kernel so that the read overlaps the arithmetic without too many
 * requests waiting at once (docs/PERFORMANCE.md, eighteenth pass). */
#define P4_PF_PARTS 3
P4_FN void p4_prefetch_next_sh(__global const float *sh, P4Idx ix, int n, int part) {
    const int total = VW * SH_NCOEF, len = total / P4_PF_PARTS, start = part * len;
    if (ix.base + 2 * VW <= n)
        prefetch_floats_l2(sh + SH_NCOEF * (ix.base + VW) + start, part == P4_PF_PARTS - 1 ? total - start : len);
}
#define P4_PREFETCH_NEXT_SH(part) p4_prefetch_next_sh(sh, ix, n, part)
#else
#define P4_PREFETCH_NEXT_SH(part) ((void)0)
#endif

__kernel void project4d(
    const int n,
    __global const float *means,     /* [N, 4] */
    __global const float *scales,    /* [N, 4] log */
    __global const float *quat_l,    /* [N, 4] */
    __global const float *quat_r,    /* [N, 4] */
    __global const float *opacity,   /* [N] logit */
    __global const float *sh,        /* [N, NT+1, SH_K, 3] */
    __global const float *phase,     /* [N, NT+1] */
    P4_VIEW_ARGS,
    __global float *means2d,         /* [N, 2] */
    __global float *conic,           /* [N, 3] */
    __global float *depth,           /* [N] */
    __global int *radius,            /* [N] */
    __global float *opac,            /* [N] */
    __global float *features,        /* [N, CHANNELS] */
    __global int *rect,              /* [N, 4] */
    __global int *tiles_touched,     /* [N] */
    __global float *color_inner)     /* [N, NT+1, 3] sum_k c[n, k, rgb] Y_k, for the adjoint */
{
    P4_INDEX_OR_RETURN(ix, n);
    P4_PREFETCH_NEXT_SH(0);
    P4Cam cam = p4_load_camera(cam_buf);
    P4State s;
    p4_forward(&cam, means, scales, quat_l, quat_r, ix, t, tiles_x, tiles_y, &s);
    P4_PREFETCH_NEXT_SH(1);
    const p4i ok = s.valid;
    if (!P4_ANY(ok)) {
        const p4f zf = 0.0f;
        const p4i zi = 0;
        for (int k = 0; k < 2; ++k) p4_st(means2d, 2, k, ix, zf);
        for (int k = 0; k < 3; ++k) p4_st(conic, 3, k, ix, zf);
        p4_st(depth, 1, 0, ix, zf); p4_sti(radius, 1, 0, ix, zi); p4_st(opac, 1, 0, ix, zf);
        for (int c = 0; c < CHANNELS; ++c) p4_st(features, CHANNELS, c, ix, zf);
        for (int k = 0; k < 4; ++k) p4_sti(rect, 4, k, ix, zi);
        p4_sti(tiles_touched, 1, 0, ix, zi);
        return;   /* culled: no colour, and color_inner is never read (the adjoint skips it) */
    }
    /* (vector: from here on, lanes of culled Gaussians store 0 through P4_SEL / P4_SELI) */
    for (int k = 0; k < 2; ++k) p4_st(means2d, 2, k, ix, P4_SEL(ok, s.means2d[k]));
    for (int k = 0; k < 3; ++k) p4_st(conic, 3, k, ix, P4_SEL(ok, s.conic[k]));
    p4_st(depth, 1, 0, ix, P4_SEL(ok, s.p[2]));
#ifdef P4_VW
    p4_sti(radius, 1, 0, ix, P4_SELI(ok, convert_intV(s.radius)));
#else
    radius[ix] = (int)s.radius;
#endif
    const p4f op = P4_SEL(ok, s.m / (1.0f + P4_EXP(-p4_ld(opacity, 1, 0, ix))));
    p4_st(opac, 1, 0, ix, op);
#ifndef P4_NO_TIGHT_RECT
    p4_tight_rect(&s, op, tiles_x, tiles_y);   /* only the tiles where alpha can reach ALPHA_MIN */
#endif
    for (int k = 0; k < 4; ++k) p4_sti(rect, 4, k, ix, P4_SELI(ok, s.rect[k]));
    p4_sti(tiles_touched, 1, 0, ix, P4_SELI(ok, (s.rect[2] - s.rect[0]) * (s.rect[3] - s.rect[1])));

    P4_PREFETCH_NEXT_SH(2);
    /* TEASH colour: max(0, 0.5 + sum_{n,k} c[n,k] Y_k(d) cos(omega_n t + phi_n)) */
    p4f d[3], Y[SH_K], cs[NT + 1], sn[NT + 1];
    p4_view_dir(&cam, &s, d);
    sh_basis(d, Y);
    teash_cos_sin(phase, ix, t, cs, sn);
    p4f out[6];
    p4f acc[3] = {0.0f, 0.0f, 0.0f};
    const int nsh = SH_NCOEF;
    p4f inner[(NT + 1) * 3];   /* [NT+1, 3] sum_k c[f, k, rgb] Y_k, k ascending */
    for (int j = 0; j < (NT + 1) * 3; ++j) inner[j] = 0.0f;
#ifdef P4_VW
    /* the coefficients (e = (f SH_K + k) 3 + c): whole blocks of VW read by rows and transposed
     * into lanes (p4_ld_rows), the rest gathered; the same sums in the same order as below */
    p4f coef[P4_NSH_ARR];
    p4_ld_rows(sh, nsh, ix, coef);
#pragma unroll
    for (int e = 0; e < nsh - nsh % VW; ++e)
        inner[3 * (e / (3 * SH_K)) + e % 3] += coef[e] * Y[(e / 3) % SH_K];
    for (int e = nsh - nsh % VW; e < nsh; ++e)
        inner[3 * (e / (3 * SH_K)) + e % 3] += p4_ld(sh, nsh, e, ix) * Y[(e / 3) % SH_K];
#else
    for (int f = 0; f <= NT; ++f)
        for (int k = 0; k < SH_K; ++k)   /* contiguous reads */
            for (int c = 0; c < 3; ++c) inner[3 * f + c] += sh[((ix * (NT + 1) + f) * SH_K + k) * 3 + c] * Y[k];
#endif
    for (int f = 0; f <= NT; ++f)
        for (int c = 0; c < 3; ++c) {
            acc[c] += inner[3 * f + c] * cs[f];
            p4_st(color_inner, (NT + 1) * 3, f * 3 + c, ix, P4_SEL(ok, inner[3 * f + c]));   /* the adjoint reads these, not sh */
        }
    for (int c = 0; c < 3; ++c) out[c] = P4_FMAX(0.5f + acc[c], (p4f)(0.0f));
    out[3] = s.p[2];
    out[4] = 0.0f; out[5] = 0.0f;
    if (has_flow) {
        p4f p2[3];
        p4_flow_point(&cam, means, ix, &s, t_flow, p2);
        p4_flow(&cam, p2, s.means2d, tiles_x, tiles_y, out + 4);   /* 0 when undefined or runaway */
    }
    for (int c = 0; c < CHANNELS; ++c) p4_st(features, CHANNELS, c, ix, (c < 6) ? P4_SEL(ok, out[c]) : (p4f)(0.0f));
}
