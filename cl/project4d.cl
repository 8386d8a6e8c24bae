/* project4d forward: one work-item per Gaussian (docs/ARCHITECTURE.md "project4d").
 * Reference: endowave_cl/reference/project.py::project4d_ref. */
#include "project4d_common.h"

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
    int i = get_global_id(0);
    if (i >= n) return;
    P4Cam cam = p4_load_camera(cam_buf);
    P4State s;
    p4_forward(&cam, means, scales, quat_l, quat_r, i, t, tiles_x, tiles_y, &s);
    if (!s.valid) {
        means2d[2 * i] = 0.0f; means2d[2 * i + 1] = 0.0f;
        for (int k = 0; k < 3; ++k) conic[3 * i + k] = 0.0f;
        depth[i] = 0.0f; radius[i] = 0; opac[i] = 0.0f;
        for (int c = 0; c < CHANNELS; ++c) features[CHANNELS * i + c] = 0.0f;
        for (int k = 0; k < 4; ++k) rect[4 * i + k] = 0;
        tiles_touched[i] = 0;
        return;   /* culled: no colour, and color_inner is never read (the adjoint skips it) */
    }
    means2d[2 * i] = s.means2d[0]; means2d[2 * i + 1] = s.means2d[1];
    for (int k = 0; k < 3; ++k) conic[3 * i + k] = s.conic[k];
    depth[i] = s.p[2];
    radius[i] = (int)s.radius;
    opac[i] = s.m / (1.0f + exp(-opacity[i]));
    for (int k = 0; k < 4; ++k) rect[4 * i + k] = s.rect[k];
    tiles_touched[i] = (s.rect[2] - s.rect[0]) * (s.rect[3] - s.rect[1]);

    /* TEASH colour: max(0, 0.5 + sum_{n,k} c[n,k] Y_k(d) cos(omega_n t + phi_n)) */
    float d[3], Y[SH_K], cs[NT + 1], sn[NT + 1];
    p4_view_dir(&cam, &s, d);
    sh_basis(d, Y);
    teash_cos_sin(phase, i, t, cs, sn);
    float out[6];
    float acc[3] = {0.0f, 0.0f, 0.0f};
    for (int f = 0; f <= NT; ++f) {
        float inner[3] = {0.0f, 0.0f, 0.0f};   /* sum_k c[f, k, rgb] Y_k: contiguous reads */
        for (int k = 0; k < SH_K; ++k)
            for (int c = 0; c < 3; ++c) inner[c] += sh[((i * (NT + 1) + f) * SH_K + k) * 3 + c] * Y[k];
        for (int c = 0; c < 3; ++c) {
            acc[c] += inner[c] * cs[f];
            color_inner[(i * (NT + 1) + f) * 3 + c] = inner[c];   /* the adjoint reads these, not sh */
        }
    }
    for (int c = 0; c < 3; ++c) out[c] = fmax(0.5f + acc[c], 0.0f);
    out[3] = s.p[2];
    out[4] = 0.0f; out[5] = 0.0f;
    if (has_flow) {
        float p2[3];
        p4_flow_point(&cam, means, i, &s, t_flow, p2);
        p4_flow(&cam, p2, s.means2d, tiles_x, tiles_y, out + 4);   /* 0 when undefined or runaway */
    }
    for (int c = 0; c < CHANNELS; ++c) features[CHANNELS * i + c] = (c < 6) ? out[c] : 0.0f;
}
