/* Device math shared by project4d.cl and project4d_bwd.cl (OpenCL C 1.2).
 *
 * Conventions (mirrored by endowave_cl/reference/project.py, which documents them):
 * - 4D rotation R = M_left(q_l) M_right(q_r), M_left(q) the matrix of v -> q * v, M_right(q) of
 *   v -> v * q, with (x, y, z, t) read as the quaternion (w, x, y, z).  4x4 matrices are row-major.
 * - Culled Gaussians: see p4_forward.
 * Build options (-D): SH_DEGREE, NT (temporal frequencies), CHANNELS, TEASH_PERIOD, MARGINAL_CULL, LOWPASS,
 * P4_VW for the vector variant, and P4_SH_FACTORS (project4d_bwd: the SH gradient as factors, sh_grad.h).
 *
 * Two variants of the same maths (endowave_cl/ops/project.py chooses one from the device queries):
 * - scalar (P4_VW undefined): one Gaussian per work-item, p4f = float; the GPU path.
 * - vector (-DP4_VW=W, W = 2, 4, 8 or 16): W consecutive Gaussians per work-item, one per lane of
 *   p4f = floatW.  CPU drivers such as PoCL do not vectorise the scalar kernels across work-items
 *   (docs/PERFORMANCE.md); here every operation works on W Gaussians at once.  Branches on a
 *   Gaussian's validity become lane masks (p4i, -1 / 0 per lane) and selects, and the builtin
 *   transcendentals, which PoCL calls out of line, are inline polynomials (p4v_exp, p4v_sincos).
 *   Lanes past N repeat Gaussian N - 1 and store nothing.
 * The functions below are written once for both: p4f / p4i are float / int or floatW / intW, and
 * every load and store of a per-Gaussian value goes through p4_ld / p4_st with a P4Idx.
 */
#ifndef ENDOWAVE_PROJECT4D_COMMON_H
#define ENDOWAVE_PROJECT4D_COMMON_H
#include "common.h"

#include "sh_grad.h"   /* SH_DEGREE, SH_K, NT, SH_NCOEF, the factored SH gradient */
#ifndef CHANNELS
#define CHANNELS 6
#endif
#ifndef TEASH_PERIOD
#define TEASH_PERIOD 2.0f   /* omega_n = 2 pi n / TEASH_PERIOD (gaussians.py) */
#endif
#ifndef MARGINAL_CULL
#define MARGINAL_CULL 0.05f /* culled when the marginal temporal weight is below this */
#endif
#ifndef LOWPASS
#define LOWPASS 0.1f        /* px^2 added to the 2D covariance diagonal (gaussians.py LOWPASS) */
#endif
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


/* ---- the per-Gaussian value type, loads and stores ------------------------------------------ */
#ifdef P4_VW
#define VW P4_VW
#include "vexp.h"   /* floatV / intV, the 16-lane convert workarounds */
typedef floatV p4f;
typedef intV p4i;
/* The functions below must be inlined for the lanes' offsets to become constants (PoCL leaves
 * plain `inline` functions with array arguments out of line).  P4_NO_FORCE_INLINE: plain inline
 * (the host sets it for Oclgrind, which cannot create the kernel when its callees are
 * always_inline; the same code otherwise). */
#ifdef P4_NO_FORCE_INLINE
#define P4_FN inline
#else
#define P4_FN inline __attribute__((always_inline))
#endif
/* The Gaussians of a work-item: lane l is Gaussian base + l; lanes below lo were done by the
 * previous work-item (the last work-item is moved back to end at N, so that every lane is a
 * Gaussian: the host runs the vector variant only for N >= VW) and store nothing. */
typedef struct {
    int base, lo;
} P4Idx;

/* LIST(E): E(lane, component) for each lane, comma-separated; STMTS(E): the same, no separators */
#if VW == 2
#define P4_LIST(E) E(0, s0), E(1, s1)
#define P4_STMTS(E) E(0, s0) E(1, s1)
#elif VW == 4
#define P4_LIST(E) E(0, s0), E(1, s1), E(2, s2), E(3, s3)
#define P4_STMTS(E) E(0, s0) E(1, s1) E(2, s2) E(3, s3)
#elif VW == 8
#define P4_LIST(E) E(0, s0), E(1, s1), E(2, s2), E(3, s3), E(4, s4), E(5, s5), E(6, s6), E(7, s7)
#define P4_STMTS(E) E(0, s0) E(1, s1) E(2, s2) E(3, s3) E(4, s4) E(5, s5) E(6, s6) E(7, s7)
#elif VW == 16
#define P4_LIST(E) E(0, s0), E(1, s1), E(2, s2), E(3, s3), E(4, s4), E(5, s5), E(6, s6), E(7, s7),    \
                   E(8, s8), E(9, s9), E(10, sa), E(11, sb), E(12, sc), E(13, sd), E(14, se), E(15, sf)
#define P4_STMTS(E) E(0, s0) E(1, s1) E(2, s2) E(3, s3) E(4, s4) E(5, s5) E(6, s6) E(7, s7)            \
                    E(8, s8) E(9, s9) E(10, sa) E(11, sb) E(12, sc) E(13, sd) E(14, se) E(15, sf)
#else
#error "P4_VW must be 2, 4, 8 or 16"
#endif

#define P4_NBLK (SH_NCOEF / VW)            /* whole blocks of VW SH coefficients per Gaussian */
#define P4_NSH_ARR (P4_NBLK > 0 ? P4_NBLK * VW : 1)   /* size of an array of them (never 0) */

/* the Gaussians of work-item g of n (n >= VW) */
P4_FN P4Idx p4_index(int g, int n) {
    P4Idx ix;
    ix.base = min(g * VW, n - VW);
    ix.lo = g * VW - ix.base;
    return ix;
}
/* A kernel's first line: this work-item's Gaussians (ix), or return when it has none. */
#define P4_INDEX_OR_RETURN(ix, n)                                                                 \
    if (get_global_id(0) * VW >= (n)) return;                                                   \
    const P4Idx ix = p4_index(get_global_id(0), (n))
#define P4_LD_LANE(l, s) q[stride * l]
#define P4_ST_LANE(l, s) if (l >= ix.lo) q[stride * l] = v.s;
#define P4_ROW_LANE(l, s) q[l]
/* element k of each lane's row of stride floats (a gather: the rows are stride floats apart) */
P4_FN p4f p4_ld(__global const float *p, int stride, int k, P4Idx ix) {
    __global const float *q = p + stride * ix.base + k;
    return (p4f)(P4_LIST(P4_LD_LANE));
}
P4_FN p4i p4_ldi(__global const int *p, int stride, int k, P4Idx ix) {
    __global const int *q = p + stride * ix.base + k;
    return (p4i)(P4_LIST(P4_LD_LANE));
}
P4_FN void p4_st(__global float *p, int stride, int k, P4Idx ix, p4f v) {
    __global float *q = p + stride * ix.base + k;
    P4_STMTS(P4_ST_LANE)
}
P4_FN void p4_sti(__global int *p, int stride, int k, P4Idx ix, p4i v) {
    __global int *q = p + stride * ix.base + k;
    P4_STMTS(P4_ST_LANE)
}

/* In-place transpose of a VW x VW block held as VW vectors (r[a] lane b <-> r[b] lane a): log2(VW)
 * rounds of even / odd shuffles; each round rotates the 2 log2(VW) bits of (vector, lane) by one. */
P4_FN void p4_transpose(p4f *r) {
    for (int round = 1; round < VW; round *= 2) {
        p4f u[VW];
#pragma unroll
        for (int a = 0; a < VW / 2; ++a) {
            u[a] = (p4f)(r[2 * a].even, r[2 * a + 1].even);
            u[VW / 2 + a] = (p4f)(r[2 * a].odd, r[2 * a + 1].odd);
        }
#pragma unroll
        for (int a = 0; a < VW; ++a) r[a] = u[a];
    }
}
/* The first nb = P4_NBLK blocks of VW floats of each lane's row of stride floats, as nb VW vectors
 * (out[j]: element j of every lane): each lane's row read in order, VW floats at a time, and each
 * VW x VW block transposed, instead of VW gathers per element.  Lane by lane rather than block by
 * block, so that the reads run through memory in order (docs/PERFORMANCE.md, third pass). */
P4_FN void p4_ld_rows(__global const float *p, int stride, P4Idx ix, p4f *out) {
    const int nb = P4_NBLK;
#pragma unroll
    for (int l = 0; l < VW; ++l)
#pragma unroll
        for (int b = 0; b < nb; ++b) {
            __global const float *q = p + stride * (ix.base + l) + VW * b;
            out[VW * b + l] = (p4f)(P4_LIST(P4_ROW_LANE));
        }
#pragma unroll
    for (int b = 0; b < nb; ++b) p4_transpose(out + VW * b);
}
/* The inverse: in[j] holds element j of every lane; each lane's first P4_NBLK VW floats are stored
 * (lanes below lo skipped), block by block: each block transposed and its VW rows stored while the
 * block is in registers (docs/PERFORMANCE.md, third pass).  in is overwritten.  P4_NT_STORE
 * (set by the host only when every row block is VW-float aligned: stride a multiple of VW, the
 * buffer aligned): one non-temporal vector store per block, which skips reading the destination's
 * cache lines first (the adjoint's v_sh is written in full and not read back here). */
#define P4_ROW_ST(l, s) q[l] = v.s;
P4_FN void p4_st_rows(__global float *p, int stride, P4Idx ix, p4f *in) {
    const int nb = P4_NBLK;
#pragma unroll
    for (int b = 0; b < nb; ++b) {
        p4_transpose(in + VW * b);
#pragma unroll
        for (int l = 0; l < VW; ++l) {
            if (l < ix.lo) continue;
            __global float *q = p + stride * (ix.base + l) + VW * b;
            const p4f v = in[VW * b + l];
#if defined(P4_NT_STORE) && P4_NT_STORE && defined(__clang__)   /* a clang builtin: plain stores elsewhere */
            __builtin_nontemporal_store(v, (__global p4f *)q);
#else
            P4_STMTS(P4_ROW_ST)
#endif
        }
    }
}
/* The 4 components of each lane's row of a [N, 4] array: VW / 4 ... 4 contiguous vectors and two
 * rounds of even / odd shuffles (out[k] lane l = p[4 (base + l) + k]) */
P4_FN void p4_ld4(__global const float *p, P4Idx ix, p4f *out) {
    __global const float *q0 = p + 4 * ix.base;
    p4f v[4];
#pragma unroll
    for (int j = 0; j < 4; ++j) {
        __global const float *q = q0 + VW * j;
        v[j] = (p4f)(P4_LIST(P4_ROW_LANE));
    }
    const p4f e0 = (p4f)(v[0].even, v[1].even), e1 = (p4f)(v[2].even, v[3].even);
    const p4f o0 = (p4f)(v[0].odd, v[1].odd), o1 = (p4f)(v[2].odd, v[3].odd);
    out[0] = (p4f)(e0.even, e1.even);
    out[1] = (p4f)(o0.even, o1.even);
    out[2] = (p4f)(e0.odd, e1.odd);
    out[3] = (p4f)(o0.odd, o1.odd);
}
#define P4_ANY(m) VANY(m)
#define P4_SEL(m, v) ((m) ? (v) : (p4f)(0.0f))      /* v where the lane mask m is set, else 0 */
#define P4_SELI(m, v) ((m) ? (v) : (p4i)(0))
#define P4_WHERE(m, v) ((m) ? (v) : (p4f)(0.0f))    /* v where m, else 0 (both variants) */
#define P4_FMAX(a, b) ((a) > (b) ? (a) : (b))       /* b where a is NaN, as fmax */
#define P4_FMIN(a, b) ((a) < (b) ? (a) : (b))
#define P4_FABS(x) as_floatV(as_intV(x) & 0x7fffffff)   /* fabs without a call (PoCL calls it) */
#define P4_ISFINITE(x) (P4_FABS(x) < (p4f)(INFINITY))
#define P4_EXP(x) p4v_exp(x)
#if defined(HOST_CLANG) && HOST_CLANG
/* sqrt lane by lane through clang's builtin, which the compiler joins into vector square roots
 * inline (cl/common.h sqrt8); PoCL's sqrt of a floatV is an out-of-line call.  The same bits. */
#define P4_SQRT_LANE(l, s) __builtin_sqrtf(x.s)
P4_FN p4f p4v_sqrt(p4f x) { return (p4f)(P4_LIST(P4_SQRT_LANE)); }
#define P4_SQRT(x) p4v_sqrt(x)
#else
#define P4_SQRT(x) sqrt(x)
#endif

#else   /* scalar: one Gaussian per work-item */
typedef float p4f;
typedef int p4i;
#define P4_FN inline
typedef int P4Idx;   /* the Gaussian */
/* A kernel's first line: this work-item's Gaussian (ix), or return past the last one. */
#define P4_INDEX_OR_RETURN(ix, n)                                                                 \
    const P4Idx ix = get_global_id(0);                                                          \
    if (ix >= (n)) return
P4_FN float p4_ld(__global const float *p, int stride, int k, P4Idx i) { return p[stride * i + k]; }
P4_FN int p4_ldi(__global const int *p, int stride, int k, P4Idx i) { return p[stride * i + k]; }
P4_FN void p4_st(__global float *p, int stride, int k, P4Idx i, float v) { p[stride * i + k] = v; }
P4_FN void p4_sti(__global int *p, int stride, int k, P4Idx i, int v) { p[stride * i + k] = v; }
P4_FN void p4_ld4(__global const float *p, P4Idx i, float *out) {
    for (int k = 0; k < 4; ++k) out[k] = p[4 * i + k];
}
#define P4_ANY(m) (m)
#define P4_SEL(m, v) (v)     /* the scalar kernels return early for culled Gaussians */
#define P4_SELI(m, v) (v)
#define P4_WHERE(m, v) ((m) ? (v) : 0.0f)
#define P4_FMAX(a, b) fmax(a, b)
#define P4_FMIN(a, b) fmin(a, b)
#define P4_ISFINITE(x) isfinite(x)
#define P4_EXP(x) exp(x)
#define P4_SQRT(x) sqrt(x)
#endif

#ifdef P4_VW
/* ---- inline transcendentals on floatV (PoCL calls the builtins out of line) ------------------- */
/* exp(x) for any x: x = k ln2 + r with k = round(x / ln2), the degree-7 polynomial of
 * EXP_NONPOS_BODY (raster_common.h), and 2^k in two factors so that k down to EXP_K_MIN gives
 * denormals / 0 and k above EXP_K_MAX infinity, as exp does.  A few ulp from exp. */
#define ROUND_MAGIC 12582912.0f   /* 1.5 2^23: (y + ROUND_MAGIC) - ROUND_MAGIC rounds |y| < 2^22 to an integer */
#define EXP_X_MAX 88.8f       /* exp(x) = inf beyond (float max ~ e^88.72) */
#define EXP_X_MIN (-104.0f)   /* exp(x) = 0 below (smallest denormal ~ e^-103.3) */
P4_FN floatV p4v_exp(floatV x) {
    const floatV xc = x > (floatV)(EXP_X_MAX) ? (floatV)(EXP_X_MAX) : (x < (floatV)(EXP_X_MIN) ? (floatV)(EXP_X_MIN) : x);
    const floatV kf = (xc * LOG2E + ROUND_MAGIC) - ROUND_MAGIC;   /* round(x / ln2), no call */
    const floatV r = (xc - kf * LN2_HI) - kf * LN2_LO;
    floatV p = (floatV)(1.0f / 5040.0f);
    p = p * r + 1.0f / 720.0f;
    p = p * r + 1.0f / 120.0f;
    p = p * r + 1.0f / 24.0f;
    p = p * r + 1.0f / 6.0f;
    p = p * r + 0.5f;
    p = p * r + 1.0f;
    p = p * r + 1.0f;
    /* 2^k = 2^k1 2^k2, k1 = k / 2, each factor a normal float for |k| <= 150 */
    const intV k = convert_intV(kf);
    const intV k1 = k >> 1, k2 = k - k1;
    const floatV e = p * as_floatV((k1 + 127) << 23) * as_floatV((k2 + 127) << 23);
    return x != x ? x : e;   /* NaN stays NaN */
}

/* cos(x) and sin(x): x = k pi/2 + r, |r| <= pi/4 (Cody-Waite with a three-part pi/2), minimax
 * polynomials of cos and sin on [-pi/4, pi/4] (Cephes sinf / cosf), and the quadrant k mod 4 picks
 * and signs them.  About 1 ulp for |x| up to a few thousand (the phases and times here are small);
 * the reduction loses accuracy as |x| grows, and past 2^22 pi / 2 the results are not sin / cos. */
#define PIO2_1 1.5703125f
#define PIO2_2 4.837512969970703125e-4f
#define PIO2_3 7.54978995489188216e-8f
#define TWO_OVER_PI 0.636619772367581343f
P4_FN void p4v_sincos(floatV x, floatV *c, floatV *s) {
    const floatV y = x * TWO_OVER_PI;
    const floatV kf = P4_FABS(y) < (floatV)(ROUND_MAGIC / 3.0f) ? (y + ROUND_MAGIC) - ROUND_MAGIC : y;   /* round(y) */
    const floatV r = ((x - kf * PIO2_1) - kf * PIO2_2) - kf * PIO2_3;
    const floatV z = r * r;
    floatV ps = (floatV)(-1.9515295891e-4f);
    ps = ps * z + 8.3321608736e-3f;
    ps = ps * z - 1.6666654611e-1f;
    const floatV sr = r + r * z * ps;                  /* sin r */
    floatV pc = (floatV)(2.443315711809948e-5f);
    pc = pc * z - 1.388731625493765e-3f;
    pc = pc * z + 4.166664568298827e-2f;
    const floatV cr = 1.0f - 0.5f * z + z * z * pc;    /* cos r */
    const intV q = convert_intV(kf) & 3;               /* x = r + q pi/2 (mod 2 pi) */
    const intV swap = (q & 1) != 0;                    /* q odd: cos x = -+sin r, sin x = +-cos r */
    const floatV cs = swap ? sr : cr, sn = swap ? cr : sr;
    *c = ((q == 1) | (q == 2)) ? -cs : cs;
    *s = (q >= 2) ? -sn : sn;
}
#define P4_SINCOS(x, c, s) p4v_sincos(x, c, s)

/* ceil(y) for finite y >= 0 without a call: floats from 2^23 up are integers */
P4_FN floatV p4v_ceil_nonneg(floatV y) {
    const floatV kf = convert_floatV(convert_intV(P4_FMIN(y, (floatV)(ROUND_MAGIC))));   /* trunc */
    return y >= (floatV)(8388608.0f) ? y : (kf < y ? kf + 1.0f : kf);
}
#else
#define P4_SINCOS(x, c, s) do { *(c) = cos(x); *(s) = sin(x); } while (0)
#endif

/* ---- camera (uniform: scalar in both variants) ---------------------------------------------- */
typedef struct {
    float R[9];
    float tv[3];
    float fx, fy, cx, cy, near;
    float campos[3];
} P4Cam;

P4_FN P4Cam p4_load_camera(__global const float *cam) {
    P4Cam c;
    for (int k = 0; k < 9; ++k) c.R[k] = cam[CAM_ROT + k];
    for (int k = 0; k < 3; ++k) c.tv[k] = cam[CAM_TRANS + k];
    c.fx = cam[CAM_FX]; c.fy = cam[CAM_FY]; c.cx = cam[CAM_CX]; c.cy = cam[CAM_CY];
    c.near = cam[CAM_NEAR];
    for (int k = 0; k < 3; ++k) c.campos[k] = cam[CAM_POS + k];
    return c;
}

/* ---- 4D rotation ---------------------------------------------------------------------------- */
P4_FN void quat_left_matrix(const p4f *q, p4f *M) {   /* v -> q * v */
    p4f a = q[0], b = q[1], c = q[2], d = q[3];
    M[0] = a;  M[1] = -b; M[2] = -c;  M[3] = -d;
    M[4] = b;  M[5] = a;  M[6] = -d;  M[7] = c;
    M[8] = c;  M[9] = d;  M[10] = a;  M[11] = -b;
    M[12] = d; M[13] = -c; M[14] = b; M[15] = a;
}

P4_FN void quat_right_matrix(const p4f *q, p4f *M) {  /* v -> v * q */
    p4f p = q[0], r1 = q[1], r2 = q[2], r3 = q[3];
    M[0] = p;   M[1] = -r1; M[2] = -r2;  M[3] = -r3;
    M[4] = r1;  M[5] = p;   M[6] = r3;   M[7] = -r2;
    M[8] = r2;  M[9] = -r3; M[10] = p;   M[11] = r1;
    M[12] = r3; M[13] = r2; M[14] = -r1; M[15] = p;
}

P4_FN void mat4_mul(const p4f *A, const p4f *B, p4f *C) {
    for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 4; ++j) {
            p4f s = 0.0f;
            for (int k = 0; k < 4; ++k) s += A[4 * i + k] * B[4 * k + j];
            C[4 * i + j] = s;
        }
}

/* q (unnormalised) -> unit q; returns |q| (clamped) */
P4_FN p4f quat_normalize(const p4f *q, p4f *u) {
    p4f n = P4_SQRT(P4_FMAX(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3], (p4f)(QUAT_NORM2_MIN)));
    for (int k = 0; k < 4; ++k) u[k] = q[k] / n;
    return n;
}

/* ---- SH / TEASH ----------------------------------------------------------------------------- */
P4_FN void sh_basis(const p4f *d, p4f *Y) {  /* unit direction [3] -> Y [SH_K] */
    p4f x = d[0], y = d[1], z = d[2];
    Y[0] = SH_C0;
#if SH_DEGREE >= 1
    Y[1] = -SH_C1 * y; Y[2] = SH_C1 * z; Y[3] = -SH_C1 * x;
#endif
#if SH_DEGREE >= 2
    p4f xx = x * x, yy = y * y, zz = z * z;
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

/* ---- the forward of one Gaussian (or one per lane), with every intermediate the adjoint needs */
typedef struct {
    p4f qln[4], qrn[4];   /* unit quaternions */
    p4f ql_norm, qr_norm; /* |q| before normalising */
    p4f Ml[16], Mr[16], R[16];
    p4f mean[4];          /* the 4D mean */
    p4f S[4];             /* exp(scales) */
    p4f M[16];            /* R diag(S) */
    p4f sxt[3], stt;      /* Sigma_xt, Sigma_tt */
    p4f dt, k;            /* t - mu_t, dt / stt */
    p4f m;                /* marginal */
    p4f mu[3];            /* conditional mean mu_x|t */
    p4f cov[9];           /* conditional covariance Sigma_x|t */
    p4f p[3];             /* camera-space mu_x|t */
    p4f T[6];             /* J W, [2, 3] */
    p4f a, b, c, det;     /* cov2d (with low-pass) and its determinant */
    p4f conic[3];
    p4f means2d[2];
    p4f radius;           /* float radius (ceil'ed) */
    p4i rect[4];
    p4i valid;            /* scalar: 0 / 1; vector: lane mask */
} P4State;

/* The tiles [rect[0], rect[2]) x [rect[1], rect[3]) (clamped to the grid) that the pixel box
 * means2d -+ (ex, ey) reaches; all zero where the lane mask valid is clear. */
P4_FN void p4_tile_rect(const p4f *means2d, p4f ex, p4f ey, p4i valid, int tiles_x, int tiles_y, p4i *rect) {
#ifdef P4_VW
    /* clamp(floor(v), 0, hi) = trunc(clamp(v, 0, hi)) and clamp(ceil(v), 0, hi) = ceil(clamp(v, 0, hi)):
     * no floor / ceil calls */
    p4f fr[4];
    fr[0] = (means2d[0] - ex) / (float)TILE;
    fr[1] = (means2d[1] - ey) / (float)TILE;
    fr[2] = (means2d[0] + ex) / (float)TILE;
    fr[3] = (means2d[1] + ey) / (float)TILE;
    for (int k = 0; k < 4; ++k) {
        const float hi = (float)((k & 1) ? tiles_y : tiles_x);
        p4f v = P4_SEL(valid, fr[k]);
        v = P4_FMIN(P4_FMAX(v, (p4f)(0.0f)), (p4f)(hi));   /* clamp(v, 0, hi); NaN -> 0 */
        if (k >= 2) v = p4v_ceil_nonneg(v);
        rect[k] = P4_SELI(valid, convert_intV(v));
    }
#else
    if (!valid) {
        for (int k = 0; k < 4; ++k) rect[k] = 0;
        return;
    }
    rect[0] = (int)clamp(floor((means2d[0] - ex) / (float)TILE), 0.0f, (float)tiles_x);
    rect[1] = (int)clamp(floor((means2d[1] - ey) / (float)TILE), 0.0f, (float)tiles_y);
    rect[2] = (int)clamp(ceil((means2d[0] + ex) / (float)TILE), 0.0f, (float)tiles_x);
    rect[3] = (int)clamp(ceil((means2d[1] + ey) / (float)TILE), 0.0f, (float)tiles_y);
#endif
}

/* Projects Gaussian(s) ix at time t.  Culled (valid = 0) when Sigma_tt <= SIGMA_TT_MIN,
 * m < MARGINAL_CULL, z < near, cov2d non-finite / not positive definite, or the tile rect empty
 * (NaN fails every test). */
P4_FN void p4_forward(const P4Cam *cam, __global const float *means, __global const float *scales,
                       __global const float *quat_l, __global const float *quat_r, P4Idx ix, float t,
                       int tiles_x, int tiles_y, P4State *s) {
    p4f q[4];
    p4f *mean = s->mean;
    p4_ld4(quat_l, ix, q);
    s->ql_norm = quat_normalize(q, s->qln);
    p4_ld4(quat_r, ix, q);
    s->qr_norm = quat_normalize(q, s->qrn);
    quat_left_matrix(s->qln, s->Ml);
    quat_right_matrix(s->qrn, s->Mr);
    mat4_mul(s->Ml, s->Mr, s->R);
    p4_ld4(scales, ix, q);
    for (int k = 0; k < 4; ++k) s->S[k] = P4_EXP(q[k]);
    p4_ld4(means, ix, mean);
    for (int r = 0; r < 4; ++r)
        for (int j = 0; j < 4; ++j) s->M[4 * r + j] = s->R[4 * r + j] * s->S[j];
    /* Sigma = M M^T; only the blocks the conditional needs */
    p4f sig[16];
    for (int r = 0; r < 4; ++r)
        for (int j = 0; j < 4; ++j) {
            p4f acc = 0.0f;
            for (int k = 0; k < 4; ++k) acc += s->M[4 * r + k] * s->M[4 * j + k];
            sig[4 * r + j] = acc;
        }
    s->stt = sig[15];
    for (int r = 0; r < 3; ++r) s->sxt[r] = sig[4 * r + 3];
    s->dt = t - mean[3];
    s->k = s->dt / s->stt;
    s->m = P4_EXP(-0.5f * s->dt * s->dt / s->stt);
    p4i valid = (s->stt > SIGMA_TT_MIN) & (s->m >= MARGINAL_CULL);
    for (int r = 0; r < 3; ++r) {
        s->mu[r] = mean[r] + s->sxt[r] * s->k;
        for (int j = 0; j < 3; ++j) s->cov[3 * r + j] = sig[4 * r + j] - s->sxt[r] * s->sxt[j] / s->stt;
    }
    for (int r = 0; r < 3; ++r)
        s->p[r] = cam->R[3 * r] * s->mu[0] + cam->R[3 * r + 1] * s->mu[1] + cam->R[3 * r + 2] * s->mu[2] + cam->tv[r];
    p4f x = s->p[0], y = s->p[1], z = s->p[2];
    valid = valid & (z >= cam->near);
    /* EWA Jacobian J of (fx x/z + cx, fy y/z + cy) (no clamping), T = J W */
    p4f j00 = cam->fx / z, j02 = -cam->fx * x / (z * z);
    p4f j11 = cam->fy / z, j12 = -cam->fy * y / (z * z);
    for (int j = 0; j < 3; ++j) {
        s->T[j] = j00 * cam->R[j] + j02 * cam->R[6 + j];
        s->T[3 + j] = j11 * cam->R[3 + j] + j12 * cam->R[6 + j];
    }
    p4f tc[6];  /* T cov, [2, 3] */
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
    p4f mid = 0.5f * (s->a + s->c);
    p4f lmax = mid + P4_SQRT(P4_FMAX(mid * mid - s->det, (p4f)(0.0f)));
    valid = valid & (s->det > 0.0f) & P4_ISFINITE(lmax) & P4_ISFINITE(s->conic[0]) & P4_ISFINITE(s->conic[1])
            & P4_ISFINITE(s->conic[2]) & P4_ISFINITE(s->means2d[0]) & P4_ISFINITE(s->means2d[1]);
    s->radius = 0.0f;
#ifdef P4_VW
    /* every lane computes its radius and rect; culled lanes (whose values may be NaN) are zeroed by
     * the selects */
    const p4f r = p4v_ceil_nonneg(3.0f * P4_SQRT(P4_SEL(valid, lmax)));
    s->radius = P4_SEL(valid, P4_FMIN(r, (p4f)(RADIUS_MAX)));
    p4_tile_rect(s->means2d, r, r, valid, tiles_x, tiles_y, s->rect);
#else
    for (int k = 0; k < 4; ++k) s->rect[k] = 0;
    if (valid) {
        const float r = ceil(3.0f * sqrt(lmax));
        s->radius = fmin(r, RADIUS_MAX);
        p4_tile_rect(s->means2d, r, r, valid, tiles_x, tiles_y, s->rect);
    }
#endif
    valid = valid & (s->rect[2] > s->rect[0]) & (s->rect[3] > s->rect[1]);
    s->valid = valid;
}

#ifndef P4_FORWARD_NO_RECT
/* An upper bound of ln(x) for a finite x > 0 (normal), without a call: x = 2^e m, m in [1, 2),
 * and log2(m) <= m - LOG2_TANGENT_OFFSET (log2 is concave: its tangent at m = 1 / ln 2 lies above
 * it, at most 0.09 above on [1, 2]). */
#define LOG2_TANGENT_OFFSET 0.913929f    /* 1 / ln 2 - log2(1 / ln 2) */
#define LN2_F 0.693147181f
P4_FN p4f p4_log_upper(p4f x) {
#ifdef P4_VW
    const intV bits = as_intV(x);
    const floatV e = as_floatV((bits >> 23) | 0x4B000000) - (8388608.0f + 127.0f);   /* exponent, exact */
    const floatV m = as_floatV((bits & 0x007fffff) | 0x3f800000);
#else
    const int bits = as_int(x);
    const float e = as_float((bits >> 23) | 0x4B000000) - (8388608.0f + 127.0f);
    const float m = as_float((bits & 0x007fffff) | 0x3f800000);
#endif
    return LN2_F * (e + m - LOG2_TANGENT_OFFSET) + 1e-3f;
}

/* The tile rect narrowed to where the Gaussian can reach alpha >= ALPHA_MIN (the rasterizers' skip
 * test): opac G >= ALPHA_MIN needs d^T cov2d^-1 d <= q = 2 ln(opac / ALPHA_MIN), i.e. |dx| <=
 * sqrt(q a), |dy| <= sqrt(q c) (a, c the 2D covariance's diagonal).  q is bounded from above
 * (p4_log_upper plus TIGHT_Q_PAD) and the box widened by TIGHT_SLACK and TIGHT_PAD pixels, so it
 * holds the rasterizers' cull box (cull_box in blend.h, with its own margins) with room for
 * rounding: the tiles it drops hold no pixel that any Gaussian-pixel test would keep, and the image
 * and gradients are those of the 3-sigma rect.  The extents are capped at the 3-sigma radius (the
 * rect never grows).  Opacities below ALPHA_MIN (with TIGHT_OPAC_SLACK) contribute nowhere: empty
 * rect.  The radius and the Gaussian's validity are not changed. */
#define TIGHT_Q_PAD 0.01f
#define TIGHT_SLACK 1.01f
#define TIGHT_PAD 0.5f
#define TIGHT_OPAC_SLACK 0.999f
P4_FN void p4_tight_rect(P4State *s, p4f opac, int tiles_x, int tiles_y) {
    const p4f ratio = opac * (1.0f / ALPHA_MIN);
    const p4i reach = s->valid & (ratio >= TIGHT_OPAC_SLACK);
    const p4f q = 2.0f * P4_FMAX(p4_log_upper(P4_FMAX(ratio, (p4f)(1.0f))), (p4f)(0.0f)) + TIGHT_Q_PAD;
    const p4f ex = P4_FMIN(P4_SQRT(q * P4_FMAX(s->a, (p4f)(0.0f))) * TIGHT_SLACK + TIGHT_PAD, s->radius);
    const p4f ey = P4_FMIN(P4_SQRT(q * P4_FMAX(s->c, (p4f)(0.0f))) * TIGHT_SLACK + TIGHT_PAD, s->radius);
    p4_tile_rect(s->means2d, ex, ey, reach, tiles_x, tiles_y, s->rect);
}
#endif

/* Camera-space position of mu_x at time t2 (flow); uses the state's Sigma_xt / Sigma_tt. */
P4_FN void p4_flow_point(const P4Cam *cam, __global const float *means, P4Idx ix, const P4State *s,
                          float t2, p4f *p2) {
    p4f k2 = (t2 - s->mean[3]) / s->stt;
    p4f mu2[3];
    for (int r = 0; r < 3; ++r) mu2[r] = s->mean[r] + s->sxt[r] * k2;
    for (int r = 0; r < 3; ++r)
        p2[r] = cam->R[3 * r] * mu2[0] + cam->R[3 * r + 1] * mu2[1] + cam->R[3 * r + 2] * mu2[2] + cam->tv[r];
}

/* The flow channel of a Gaussian: proj(p2) - means2d, p2 = its conditional mean at the flow time
 * in camera space.  Returns 0 (flow 0, no gradient) when p2 is behind the near plane (no
 * projection) or when the flow exceeds the image size in x or y (TILE * max(tiles_x, tiles_y)):
 * a Gaussian that would cross the whole image between two frames has a runaway velocity
 * Sigma_xt / Sigma_tt, and its flow, thousands of pixels, cannot be matched by any pseudo ground
 * truth; left in, it took over the flow loss in training (README, "Flow loss").
 * Returns the (lane) mask of Gaussians whose flow is defined. */
P4_FN p4i p4_flow(const P4Cam *cam, const p4f *p2, const p4f *means2d, int tiles_x, int tiles_y,
                   p4f *flow) {
    const float fmax_px = (float)(TILE * max(tiles_x, tiles_y));
#ifdef P4_VW
    const p4f f0 = cam->fx * p2[0] / p2[2] + cam->cx - means2d[0];
    const p4f f1 = cam->fy * p2[1] / p2[2] + cam->cy - means2d[1];
    const p4i ok = (p2[2] >= cam->near) & (P4_FABS(f0) <= fmax_px) & (P4_FABS(f1) <= fmax_px);
    flow[0] = P4_SEL(ok, f0); flow[1] = P4_SEL(ok, f1);
    return ok;
#else
    flow[0] = 0.0f; flow[1] = 0.0f;
    if (!(p2[2] >= cam->near)) return 0;
    const float f0 = cam->fx * p2[0] / p2[2] + cam->cx - means2d[0];
    const float f1 = cam->fy * p2[1] / p2[2] + cam->cy - means2d[1];
    if (!(fabs(f0) <= fmax_px && fabs(f1) <= fmax_px)) return 0;
    flow[0] = f0; flow[1] = f1;
    return 1;
#endif
}

/* SH direction: normalize(mu_x|t - campos) */
P4_FN void p4_view_dir(const P4Cam *cam, const P4State *s, p4f *d) {
    p4f v0 = s->mu[0] - cam->campos[0], v1 = s->mu[1] - cam->campos[1], v2 = s->mu[2] - cam->campos[2];
    p4f n = P4_SQRT(v0 * v0 + v1 * v1 + v2 * v2);
    d[0] = v0 / n; d[1] = v1 / n; d[2] = v2 / n;
}

/* cos(omega_n t + phi_n) and sin(...) for n = 0..NT (n = 0: cos 1, sin 0) */
P4_FN void teash_cos_sin(__global const float *phase, P4Idx ix, float t, p4f *cs, p4f *sn) {
    cs[0] = 1.0f; sn[0] = 0.0f;
    for (int n = 1; n <= NT; ++n) {
        p4f arg = TWO_PI_F * (float)n / TEASH_PERIOD * t + p4_ld(phase, NT + 1, n, ix);
        P4_SINCOS(arg, &cs[n], &sn[n]);
    }
}

#endif
