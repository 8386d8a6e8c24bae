/* Device math shared by project4d.cl and project4d_bwd.cl (OpenCL C 1.2).
 *
 * Conventions (mirrored by endowave_cl/reference/project.py, which documents them):
 * - 4D rotation R = M_left(q_l) M_right(q_r), M_left(q) the matrix of v -> q * v, M_right(q) of
 *   v -> v * q, with (x, y, z, t) read as the quaternion (w, x, y, z).  4x4 matrices are row-major.
 * - Culled Gaussians: see p4_forward.
 * Build options (-D): SH_DEGREE, NT (temporal frequencies), CHANNELS, TEASH_PERIOD, MARGINAL_CULL.
 */
#ifndef ENDOWAVE_PROJECT4D_COMMON_H
#define ENDOWAVE_PROJECT4D_COMMON_H
#include "common.h"

#ifndef SH_DEGREE
#define SH_DEGREE 3
#endif
#define SH_K ((SH_DEGREE + 1) * (SH_DEGREE + 1))   /* SH bases per temporal frequency */
#ifndef NT
#define NT 2
#endif
#ifndef CHANNELS
#define CHANNELS 6
#endif
#ifndef TEASH_PERIOD
#define TEASH_PERIOD 2.0f   /* omega_n = 2 pi n / TEASH_PERIOD (gaussians.py) */
#endif
#ifndef MARGINAL_CULL
#define MARGINAL_CULL 0.05f /* culled when the marginal temporal weight is below this */
#endif
#define LOWPASS 0.3f               /* 3DGS low-pass added to the 2D covariance diagonal */
#define SIGMA_TT_MIN 1e-12f        /* degenerate temporal variance: culled */
#define RADIUS_MAX 1073741824.0f   /* stored int radius saturates at 2^30 */
#define QUAT_NORM2_MIN 1e-24f      /* |q|^2 clamp so that q = 0 gives no NaN */
#define TWO_PI_F 6.28318530717958647f

/* 3DGS real-SH constants */
#define SH_C0 0.28209479177387814f
#define SH_C1 0.4886025119029199f
#define SH_C2_0 1.0925484305920792f
#define SH_C2_1 (-1.0925484305920792f)
#define SH_C2_2 0.31539156525252005f
#define SH_C2_3 (-1.0925484305920792f)
#define SH_C2_4 0.5462742152960396f
#define SH_C3_0 (-0.5900435899266435f)
#define SH_C3_1 2.890611442640554f
#define SH_C3_2 (-0.4570457994644658f)
#define SH_C3_3 0.3731763325901154f
#define SH_C3_4 (-0.4570457994644658f)
#define SH_C3_5 1.445305721320277f
#define SH_C3_6 (-0.5900435899266435f)

/* Camera buffer layout (endowave_cl/ops/project.py writes it): */
#define CAM_ROT 0      /* 9 floats, world -> camera rotation, row-major */
#define CAM_TRANS 9    /* 3 floats */
#define CAM_FX 12
#define CAM_FY 13
#define CAM_CX 14
#define CAM_CY 15
#define CAM_NEAR 16
#define CAM_POS 17     /* 3 floats, camera centre in world coordinates */
#define CAM_SIZE 20

/* The arguments of both kernels after the per-Gaussian inputs: the camera, the times and the grid */
#define P4_VIEW_ARGS                                                                       \
    __global const float *cam_buf,   /* [CAM_SIZE] */                                     \
    const float t,                   /* render time */                                    \
    const float t_flow,              /* flow target time (when has_flow) */               \
    const int has_flow,                                                                   \
    const int tiles_x,                                                                    \
    const int tiles_y

typedef struct {
    float R[9];
    float tv[3];
    float fx, fy, cx, cy, near;
    float campos[3];
} P4Cam;

inline P4Cam p4_load_camera(__global const float *cam) {
    P4Cam c;
    for (int k = 0; k < 9; ++k) c.R[k] = cam[CAM_ROT + k];
    for (int k = 0; k < 3; ++k) c.tv[k] = cam[CAM_TRANS + k];
    c.fx = cam[CAM_FX]; c.fy = cam[CAM_FY]; c.cx = cam[CAM_CX]; c.cy = cam[CAM_CY];
    c.near = cam[CAM_NEAR];
    for (int k = 0; k < 3; ++k) c.campos[k] = cam[CAM_POS + k];
    return c;
}

/* ---- 4D rotation ---------------------------------------------------------------------------- */
inline void quat_left_matrix(const float *q, float *M) {   /* v -> q * v */
    float a = q[0], b = q[1], c = q[2], d = q[3];
    M[0] = a;  M[1] = -b; M[2] = -c;  M[3] = -d;
    M[4] = b;  M[5] = a;  M[6] = -d;  M[7] = c;
    M[8] = c;  M[9] = d;  M[10] = a;  M[11] = -b;
    M[12] = d; M[13] = -c; M[14] = b; M[15] = a;
}

inline void quat_right_matrix(const float *q, float *M) {  /* v -> v * q */
    float p = q[0], r1 = q[1], r2 = q[2], r3 = q[3];
    M[0] = p;   M[1] = -r1; M[2] = -r2;  M[3] = -r3;
    M[4] = r1;  M[5] = p;   M[6] = r3;   M[7] = -r2;
    M[8] = r2;  M[9] = -r3; M[10] = p;   M[11] = r1;
    M[12] = r3; M[13] = r2; M[14] = -r1; M[15] = p;
}

inline void mat4_mul(const float *A, const float *B, float *C) {
    for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 4; ++j) {
            float s = 0.0f;
            for (int k = 0; k < 4; ++k) s += A[4 * i + k] * B[4 * k + j];
            C[4 * i + j] = s;
        }
}

/* q (unnormalised) -> unit q; returns |q| (clamped) */
inline float quat_normalize(const float *q, float *u) {
    float n = sqrt(fmax(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3], QUAT_NORM2_MIN));
    for (int k = 0; k < 4; ++k) u[k] = q[k] / n;
    return n;
}

/* ---- SH / TEASH ----------------------------------------------------------------------------- */
inline void sh_basis(const float *d, float *Y) {  /* unit direction [3] -> Y [SH_K] */
    float x = d[0], y = d[1], z = d[2];
    Y[0] = SH_C0;
#if SH_DEGREE >= 1
    Y[1] = -SH_C1 * y; Y[2] = SH_C1 * z; Y[3] = -SH_C1 * x;
#endif
#if SH_DEGREE >= 2
    float xx = x * x, yy = y * y, zz = z * z;
    Y[4] = SH_C2_0 * x * y;
    Y[5] = SH_C2_1 * y * z;
    Y[6] = SH_C2_2 * (2.0f * zz - xx - yy);
    Y[7] = SH_C2_3 * x * z;
    Y[8] = SH_C2_4 * (xx - yy);
#endif
#if SH_DEGREE >= 3
    Y[9] = SH_C3_0 * y * (3.0f * xx - yy);
    Y[10] = SH_C3_1 * x * y * z;
    Y[11] = SH_C3_2 * y * (4.0f * zz - xx - yy);
    Y[12] = SH_C3_3 * z * (2.0f * zz - 3.0f * xx - 3.0f * yy);
    Y[13] = SH_C3_4 * x * (4.0f * zz - xx - yy);
    Y[14] = SH_C3_5 * z * (xx - yy);
    Y[15] = SH_C3_6 * x * (xx - 3.0f * yy);
#endif
#if SH_DEGREE > 3
#error "SH_DEGREE > 3 is not supported"
#endif
}

/* ---- the forward of one Gaussian, with every intermediate the adjoint needs ------------------ */
typedef struct {
    float qln[4], qrn[4];   /* unit quaternions */
    float ql_norm, qr_norm; /* |q| before normalising */
    float Ml[16], Mr[16], R[16];
    float S[4];             /* exp(scales) */
    float M[16];            /* R diag(S) */
    float sxt[3], stt;      /* Sigma_xt, Sigma_tt */
    float dt, k;            /* t - mu_t, dt / stt */
    float m;                /* marginal */
    float mu[3];            /* conditional mean mu_x|t */
    float cov[9];           /* conditional covariance Sigma_x|t */
    float p[3];             /* camera-space mu_x|t */
    float T[6];             /* J W, [2, 3] */
    float a, b, c, det;     /* cov2d (with low-pass) and its determinant */
    float conic[3];
    float means2d[2];
    float radius;           /* float radius (ceil'ed) */
    int rect[4];
    int valid;
} P4State;

/* Projects Gaussian i at time t.  Culled (valid = 0) when Sigma_tt <= SIGMA_TT_MIN, m < MARGINAL_CULL,
 * z < near, cov2d non-finite / not positive definite, or the tile rect empty (NaN fails every test). */
inline void p4_forward(const P4Cam *cam, __global const float *means, __global const float *scales,
                       __global const float *quat_l, __global const float *quat_r, int i, float t,
                       int tiles_x, int tiles_y, P4State *s) {
    float q[4], mean[4];
    for (int k = 0; k < 4; ++k) q[k] = quat_l[4 * i + k];
    s->ql_norm = quat_normalize(q, s->qln);
    for (int k = 0; k < 4; ++k) q[k] = quat_r[4 * i + k];
    s->qr_norm = quat_normalize(q, s->qrn);
    quat_left_matrix(s->qln, s->Ml);
    quat_right_matrix(s->qrn, s->Mr);
    mat4_mul(s->Ml, s->Mr, s->R);
    for (int k = 0; k < 4; ++k) { s->S[k] = exp(scales[4 * i + k]); mean[k] = means[4 * i + k]; }
    for (int r = 0; r < 4; ++r)
        for (int j = 0; j < 4; ++j) s->M[4 * r + j] = s->R[4 * r + j] * s->S[j];
    /* Sigma = M M^T; only the blocks the conditional needs */
    float sig[16];
    for (int r = 0; r < 4; ++r)
        for (int j = 0; j < 4; ++j) {
            float acc = 0.0f;
            for (int k = 0; k < 4; ++k) acc += s->M[4 * r + k] * s->M[4 * j + k];
            sig[4 * r + j] = acc;
        }
    s->stt = sig[15];
    for (int r = 0; r < 3; ++r) s->sxt[r] = sig[4 * r + 3];
    s->dt = t - mean[3];
    s->k = s->dt / s->stt;
    s->m = exp(-0.5f * s->dt * s->dt / s->stt);
    int valid = (s->stt > SIGMA_TT_MIN) && (s->m >= MARGINAL_CULL);
    for (int r = 0; r < 3; ++r) {
        s->mu[r] = mean[r] + s->sxt[r] * s->k;
        for (int j = 0; j < 3; ++j) s->cov[3 * r + j] = sig[4 * r + j] - s->sxt[r] * s->sxt[j] / s->stt;
    }
    for (int r = 0; r < 3; ++r)
        s->p[r] = cam->R[3 * r] * s->mu[0] + cam->R[3 * r + 1] * s->mu[1] + cam->R[3 * r + 2] * s->mu[2] + cam->tv[r];
    float x = s->p[0], y = s->p[1], z = s->p[2];
    valid = valid && (z >= cam->near);
    /* EWA Jacobian J of (fx x/z + cx, fy y/z + cy) (no clamping), T = J W */
    float j00 = cam->fx / z, j02 = -cam->fx * x / (z * z);
    float j11 = cam->fy / z, j12 = -cam->fy * y / (z * z);
    for (int j = 0; j < 3; ++j) {
        s->T[j] = j00 * cam->R[j] + j02 * cam->R[6 + j];
        s->T[3 + j] = j11 * cam->R[3 + j] + j12 * cam->R[6 + j];
    }
    float tc[6];  /* T cov, [2, 3] */
    for (int r = 0; r < 2; ++r)
        for (int j = 0; j < 3; ++j)
            tc[3 * r + j] = s->T[3 * r] * s->cov[j] + s->T[3 * r + 1] * s->cov[3 + j] + s->T[3 * r + 2] * s->cov[6 + j];
    s->a = tc[0] * s->T[0] + tc[1] * s->T[1] + tc[2] * s->T[2] + LOWPASS;
    s->b = tc[0] * s->T[3] + tc[1] * s->T[4] + tc[2] * s->T[5];
    s->c = tc[3] * s->T[3] + tc[4] * s->T[4] + tc[5] * s->T[5] + LOWPASS;
    s->det = s->a * s->c - s->b * s->b;
    s->conic[0] = s->c / s->det;
    s->conic[1] = -s->b / s->det;
    s->conic[2] = s->a / s->det;
    s->means2d[0] = cam->fx * x / z + cam->cx;
    s->means2d[1] = cam->fy * y / z + cam->cy;
#ifdef P4_FORWARD_NO_RECT
    /* the adjoint takes validity from the forward's radius: radius / rect are not needed (means2d
     * is: p4_flow tests the flow against it) */
    s->valid = valid;
    return;
#endif
    float mid = 0.5f * (s->a + s->c);
    float lmax = mid + sqrt(fmax(mid * mid - s->det, 0.0f));
    valid = valid && (s->det > 0.0f) && isfinite(lmax) && isfinite(s->conic[0]) && isfinite(s->conic[1])
            && isfinite(s->conic[2]) && isfinite(s->means2d[0]) && isfinite(s->means2d[1]);
    s->radius = 0.0f;
    for (int k = 0; k < 4; ++k) s->rect[k] = 0;
    if (valid) {
        float r = ceil(3.0f * sqrt(lmax));
        float fx0 = clamp(floor((s->means2d[0] - r) / (float)TILE), 0.0f, (float)tiles_x);
        float fx1 = clamp(ceil((s->means2d[0] + r) / (float)TILE), 0.0f, (float)tiles_x);
        float fy0 = clamp(floor((s->means2d[1] - r) / (float)TILE), 0.0f, (float)tiles_y);
        float fy1 = clamp(ceil((s->means2d[1] + r) / (float)TILE), 0.0f, (float)tiles_y);
        s->rect[0] = (int)fx0; s->rect[1] = (int)fy0; s->rect[2] = (int)fx1; s->rect[3] = (int)fy1;
        s->radius = fmin(r, RADIUS_MAX);
        valid = (s->rect[2] > s->rect[0]) && (s->rect[3] > s->rect[1]);
    }
    s->valid = valid;
}

/* Camera-space position of mu_x at time t2 (flow); uses the state's Sigma_xt / Sigma_tt. */
inline void p4_flow_point(const P4Cam *cam, __global const float *means, int i, const P4State *s,
                          float t2, float *p2) {
    float k2 = (t2 - means[4 * i + 3]) / s->stt;
    float mu2[3];
    for (int r = 0; r < 3; ++r) mu2[r] = means[4 * i + r] + s->sxt[r] * k2;
    for (int r = 0; r < 3; ++r)
        p2[r] = cam->R[3 * r] * mu2[0] + cam->R[3 * r + 1] * mu2[1] + cam->R[3 * r + 2] * mu2[2] + cam->tv[r];
}

/* The flow channel of a Gaussian: proj(p2) - means2d, p2 = its conditional mean at the flow time
 * in camera space.  Returns 0 (flow 0, no gradient) when p2 is behind the near plane (no
 * projection) or when the flow exceeds the image size in x or y (TILE * max(tiles_x, tiles_y)):
 * a Gaussian that would cross the whole image between two frames has a runaway velocity
 * Sigma_xt / Sigma_tt, and its flow, thousands of pixels, cannot be matched by any pseudo ground
 * truth; left in, it took over the flow loss in training (README, "Flow loss"). */
inline int p4_flow(const P4Cam *cam, const float *p2, const float *means2d, int tiles_x, int tiles_y,
                   float *flow) {
    flow[0] = 0.0f; flow[1] = 0.0f;
    if (!(p2[2] >= cam->near)) return 0;
    const float f0 = cam->fx * p2[0] / p2[2] + cam->cx - means2d[0];
    const float f1 = cam->fy * p2[1] / p2[2] + cam->cy - means2d[1];
    const float fmax_px = (float)(TILE * max(tiles_x, tiles_y));
    if (!(fabs(f0) <= fmax_px && fabs(f1) <= fmax_px)) return 0;
    flow[0] = f0; flow[1] = f1;
    return 1;
}

/* SH direction: normalize(mu_x|t - campos) */
inline void p4_view_dir(const P4Cam *cam, const P4State *s, float *d) {
    float v0 = s->mu[0] - cam->campos[0], v1 = s->mu[1] - cam->campos[1], v2 = s->mu[2] - cam->campos[2];
    float n = sqrt(v0 * v0 + v1 * v1 + v2 * v2);
    d[0] = v0 / n; d[1] = v1 / n; d[2] = v2 / n;
}

/* cos(omega_n t + phi_n) and sin(...) for n = 0..NT (n = 0: cos 1, sin 0) */
inline void teash_cos_sin(__global const float *phase, int i, float t, float *cs, float *sn) {
    cs[0] = 1.0f; sn[0] = 0.0f;
    for (int n = 1; n <= NT; ++n) {
        float arg = TWO_PI_F * (float)n / TEASH_PERIOD * t + phase[(NT + 1) * i + n];
        cs[n] = cos(arg);
        sn[n] = sin(arg);
    }
}

#endif
