/* Rational-wavelet transform kernels (OpenCL C 1.2): separable convolution along one axis,
 * rational resampling along one axis, their adjoints, and the small element-wise and reduction
 * kernels of the wavelet loss.  Host side and conventions: endowave_cl/wavelet/ops.py and
 * endowave_cl/wavelet/filters.py (docs/WAVELET.md).
 *
 * Axis-generic layout: a contiguous array is viewed as [outer, n, inner] and the operation runs
 * along the middle axis.  For a channel-last image [H, W, C]: rows (along W) are
 * outer = H, n = W, inner = C; columns (along H) are outer = 1, n = H, inner = W * C.
 * Global range: dimension 0 = x * inner + k (contiguous in memory; a work-item takes a run of
 * consecutive elements), dimension 1 = o; the element's flat index is o * n * inner + x * inner + k.
 * The convolutions run over a stack of such arrays (slots), with dimension 2 = the output slot.
 */
#include "common.h"

/* The resampling kernels take the factor a = RP / RQ as build options, so that their divisions
 * by p and q are by constants (endowave_cl/wavelet/ops.py sets them). */
#ifndef RP
#define RP 3
#endif
#ifndef RQ
#define RQ 2
#endif

/* Whole-sample symmetric reflection of position m into [0, n): -1 -> 1, n -> n - 2, repeated.
 * One reflection (|m| < n, m < 2 n - 1: every border tap of an axis longer than the filter's
 * radius) without the integer division, which PoCL runs per tap of every border element. */
inline int reflect_idx(int m, int n) {
    if (n == 1) return 0;
    if (m > -n && m < 2 * n - 1) return m < 0 ? -m : (m < n ? m : 2 * (n - 1) - m);
    int period = 2 * (n - 1);
    int r = m % period;
    if (r < 0) r += period;
    return r < n ? r : period - r;
}

/* The convolution kernels compute CONV_RUN consecutive elements of a line per work-item (a build
 * option, 8 or 16: endowave_cl/wavelet/ops.py conv_run chooses it per device): in the interior (no
 * reflection) each tap is then one or two 8-wide loads (load8, common.h) and multiply-adds for all
 * of them, the same operations in the same order as the per-element path.  Runs at the border of
 * the axis take 8-wide paths too (conv_elem8 / conv_gather8 and their adjoints, the same taps in
 * the same order), the per-element path only what is left (a line's last, shorter run; axes
 * shorter than the filter).  (With one element per work-item PoCL ran a serial chain of scalar
 * multiply-adds; with 16 each tap's value feeds two vectors and there are half as many
 * work-items.) */
#ifndef CONV_RUN
#define CONV_RUN 16
#endif
#if CONV_RUN != 8 && CONV_RUN != 16
#error "CONV_RUN must be 8 or 16"
#endif

/* 8 consecutive floats of local memory (load8 of common.h for a staged line). */
inline float8 load8_l(__local const float *p) {
    return (float8)(p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7]);
}

/* conv_run8<S>: sum_i f[i] src[(i - R) step] for the 8 elements src[0 .. 7]: an interior run of
 * conv_axis (step = -inner) or of conv_axis_bwd (step = +inner), R = flen / 2.  conv_run16<S>: the
 * same for the 16 elements src[0 .. 15], as two 8-wide halves sharing each tap's load.  Written once
 * for src in global memory (S empty) and in local memory (S = _l: the staged row passes below). */
#define CONV_RUNS(S, AS, LOAD)                                                                   \
inline float8 conv_run8##S(AS const float *src, __global const float *f, int flen, int step) {  \
    const int R = flen / 2;                                                                      \
    float8 acc = (float8)(0.0f);                                                                 \
    for (int i = 0; i < flen; ++i)                                                               \
        acc += f[i] * LOAD(src + (i - R) * step);                                                \
    return acc;                                                                                  \
}                                                                                                \
inline void conv_run16##S(AS const float *src, __global const float *f, int flen, int step,     \
                          float8 *lo, float8 *hi) {                                              \
    const int R = flen / 2;                                                                      \
    float8 a = (float8)(0.0f), b = (float8)(0.0f);                                               \
    for (int i = 0; i < flen; ++i) {                                                             \
        const float fi = f[i];                                                                   \
        AS const float *p = src + (i - R) * step;                                                \
        a += fi * LOAD(p);                                                                       \
        b += fi * LOAD(p + 8);                                                                   \
    }                                                                                            \
    *lo = a;                                                                                     \
    *hi = b;                                                                                     \
}
CONV_RUNS(, __global, load8)
CONV_RUNS(_l, __local, load8_l)

/* sum_i f[i] line[reflect(x - (i - R)) * inner] (zero_border: the taps outside [0, n) dropped):
 * one element of conv_axis; line = &in[o, 0, k]. */
inline float conv_elem(__global const float *line, __global const float *f, int flen, int n, int inner,
                       int x, int zero_border) {
    const int R = flen / 2;
    float acc = 0.0f;
    if (x - R >= 0 && x + R < n) {          /* interior: no reflection needed */
        for (int i = 0; i < flen; ++i)
            acc += f[i] * line[(size_t)(x - i + R) * inner];
    } else if (zero_border) {
        for (int i = 0; i < flen; ++i) {
            const int m = x - i + R;
            if (m >= 0 && m < n) acc += f[i] * line[(size_t)m * inner];
        }
    } else {
        for (int i = 0; i < flen; ++i)
            acc += f[i] * line[(size_t)reflect_idx(x - i + R, n) * inner];
    }
    return acc;
}

/* conv_elem for the 8 consecutive elements line[k .. k + 7] of one position x (a run that does not
 * cross a position: inner >= 8): the same taps, source positions and order, so the same bits as 8
 * calls of conv_elem, with one 8-wide load per tap.  The border runs of a column pass (inner = the
 * image's row) take this path: R of every n positions at each end, which with scalar loads took as
 * long as the whole interior of a 256-row image. */
inline float8 conv_elem8(__global const float *line, __global const float *f, int flen, int n, int inner,
                         int x, int zero_border) {
    const int R = flen / 2;
    float8 acc = (float8)(0.0f);
    for (int i = 0; i < flen; ++i) {
        const int m = x - i + R;
        if (zero_border) {
            if (m >= 0 && m < n) acc += f[i] * load8(line + (size_t)m * inner);
        } else {
            acc += f[i] * load8(line + (size_t)reflect_idx(m, n) * inner);
        }
    }
    return acc;
}

/* line[src.s0 .. src.s7] as one vector (the gathers of the row passes' border runs). */
inline float8 gather8(__global const float *line, int8 src) {
    return (float8)(line[src.s0], line[src.s1], line[src.s2], line[src.s3],
                    line[src.s4], line[src.s5], line[src.s6], line[src.s7]);
}

/* select(a, b, c) for lane masks c of -1 / 0 (what vector comparisons give) as bit operations:
 * the same lanes, where PoCL calls select out of line (a call per tap of a border run). */
inline int8 sel_i8(int8 a, int8 b, int8 c) { return (b & c) | (a & ~c); }
inline float8 sel_f8(float8 a, float8 b, int8 c) { return as_float8((as_int8(b) & c) | (as_int8(a) & ~c)); }

/* conv_elem for the 8 consecutive flat elements xi .. xi + 7 of a line (line = &in[o, 0, 0]) that
 * may span positions (a row pass: inner < 8), for an axis longer than the filter's radius (n > R: one
 * reflection at most): per tap, the 8 source indices as a vector, the values gathered.  The same
 * taps in the same order as conv_elem; a zero-border tap outside [0, n) adds 0 where conv_elem
 * skips it (the same value, up to the sign of a zero sum). */
inline float8 conv_gather8(__global const float *line, __global const float *f, int flen, int n, int inner,
                           int xi, int zero_border) {
    const int R = flen / 2;
    const int8 e = (int8)(xi) + (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    const int8 x = e / inner;
    const int8 k = e - x * inner;
    float8 acc = (float8)(0.0f);
    for (int i = 0; i < flen; ++i) {
        int8 m = x + (int8)(R - i);
        const int8 inside = (m >= (int8)(0)) & (m < (int8)(n));
        m = sel_i8(m, -m, m < (int8)(0));          /* reflect (zero border: masked out below) */
        m = sel_i8(m, (int8)(2 * (n - 1)) - m, m >= (int8)(n));
        const int8 src = m * inner + k;
        float8 v = gather8(line, src);
        if (zero_border) v = sel_f8((float8)(0.0f), v, inside);
        acc += f[i] * v;
    }
    return acc;
}

/* v_conv_elem (below) for the 8 consecutive elements line[k .. k + 7] of one position y: the same
 * terms in the same order, one 8-wide load each. */
inline float8 v_conv_elem8(__global const float *line, __global const float *f, int flen, int n, int inner,
                           int y) {
    const int R = flen / 2;
    float8 acc = (float8)(0.0f);
    const int lo = -R, hi = n - 1 + R;
    if (n == 1) {
        for (int m = lo; m <= hi; ++m)
            for (int i = 0; i < flen; ++i) {
                const int x = m + i - R;
                if (x >= 0 && x < n) acc += f[i] * load8(line + (size_t)x * inner);
            }
        return acc;
    }
    const int P = 2 * (n - 1);
    const int nres = (y == 0 || y == n - 1) ? 1 : 2;
    for (int s = 0; s < nres; ++s) {
        const int r = (s == 0) ? y : P - y;
        int m = r - ((r - lo) / P) * P;
        for (; m <= hi; m += P)
            for (int i = 0; i < flen; ++i) {
                const int x = m + i - R;
                if (x >= 0 && x < n) acc += f[i] * load8(line + (size_t)x * inner);
            }
    }
    return acc;
}

/* The stacked convolutions: input and output are stacks of equally shaped slots [outer, n, inner]
 * (slot = outer * n * inner floats), f a stack of filters [*, flen], and output slot t is a sum of
 * terms, each the convolution of one input slot with one filter:
 *     terms[t * term_stride] = the number of terms (>= 1), then per term c
 *     terms[t * term_stride + 1 + 2 c] = its input slot, terms[t * term_stride + 2 + 2 c] = its filter.
 * The terms are added in their order after each is summed over its taps, so one term is exactly the
 * single convolution and several are the sum of single convolutions, bit for bit.  One launch does a
 * whole level's filtering along one axis (endowave_cl/wavelet/ops.py conv_axis_stack). */
#define TERM_SRC(tt, c) (tt)[1 + 2 * (c)]
#define TERM_FILTER(tt, c) (tt)[2 + 2 * (c)]

/* out[t, o, x, k] = sum over the terms (s, g) of t of sum_i f[g, i] in[s, o, reflect(x - (i - R)), k],
 * R = flen / 2 (flen odd); with zero_border != 0 the positions outside [0, n) count as zeros instead
 * (zero padding, the blur of the SSIM loss).  Work-item (u, o, t) computes the flat elements
 * x * inner + k = u * CONV_RUN ... u * CONV_RUN + CONV_RUN - 1 of line o of output slot t. */
__kernel void conv_axis(__global const float *in, __global float *out,
                        __global const float *f, const int flen,
                        const int outer, const int n, const int inner, const int zero_border,
                        __global const int *terms, const int term_stride) {
    const int xi0 = get_global_id(0) * CONV_RUN;    /* first x * inner + k of this work-item */
    const int o = get_global_id(1);
    const int t = get_global_id(2);
    const int len = n * inner;
    if (xi0 >= len || o >= outer) return;
    const int R = flen / 2;
    const size_t slot = (size_t)outer * len;
    __global const int *tt = terms + t * term_stride;
    const int nterm = tt[0];
    __global float *out_o = out + t * slot + (size_t)o * len;
    /* xi0 / inner >= R and (xi0 + CONV_RUN - 1) / inner < n - R, without the divisions */
    if (xi0 + CONV_RUN <= len && xi0 >= R * inner && xi0 + CONV_RUN - 1 < (n - R) * inner) {
        /* interior run: element xi reads in_o[xi + (R - i) inner] for tap i */
#if CONV_RUN == 16
        float8 lo = (float8)(0.0f), hi = (float8)(0.0f);
        for (int c = 0; c < nterm; ++c) {
            float8 a, b;
            conv_run16(in + TERM_SRC(tt, c) * slot + (size_t)o * len + xi0, f + TERM_FILTER(tt, c) * flen,
                       flen, -inner, &a, &b);
            lo = c ? lo + a : a;
            hi = c ? hi + b : b;
        }
        store8(out_o + xi0, lo);
        store8(out_o + xi0 + 8, hi);
#else
        float8 acc = (float8)(0.0f);
        for (int c = 0; c < nterm; ++c) {
            const float8 a = conv_run8(in + TERM_SRC(tt, c) * slot + (size_t)o * len + xi0,
                                       f + TERM_FILTER(tt, c) * flen, flen, -inner);
            acc = c ? acc + a : a;
        }
        store8(out_o + xi0, acc);
#endif
    } else if (xi0 - (xi0 / inner) * inner + CONV_RUN <= inner) {
        /* a border run within one position x (a column pass): 8 elements at a time */
        const int x = xi0 / inner, k0 = xi0 - x * inner;
        for (int h = 0; h < CONV_RUN; h += 8) {
            float8 acc = (float8)(0.0f);
            for (int c = 0; c < nterm; ++c) {
                const float8 e = conv_elem8(in + TERM_SRC(tt, c) * slot + (size_t)o * len + k0 + h,
                                            f + TERM_FILTER(tt, c) * flen, flen, n, inner, x, zero_border);
                acc = c ? acc + e : e;
            }
            store8(out_o + xi0 + h, acc);
        }
    } else if (xi0 + CONV_RUN <= len && n > R) {
        /* a border run across positions (a row pass): 8 elements at a time, gathered */
        for (int h = 0; h < CONV_RUN; h += 8) {
            float8 acc = (float8)(0.0f);
            for (int c = 0; c < nterm; ++c) {
                const float8 e = conv_gather8(in + TERM_SRC(tt, c) * slot + (size_t)o * len,
                                              f + TERM_FILTER(tt, c) * flen, flen, n, inner, xi0 + h, zero_border);
                acc = c ? acc + e : e;
            }
            store8(out_o + xi0 + h, acc);
        }
    } else {
        const int end = xi0 + CONV_RUN < len ? xi0 + CONV_RUN : len;
        for (int xi = xi0; xi < end; ++xi) {
            const int x = xi / inner;
            float acc = 0.0f;
            for (int c = 0; c < nterm; ++c) {
                const float e = conv_elem(in + TERM_SRC(tt, c) * slot + (size_t)o * len + (xi - x * inner),
                                          f + TERM_FILTER(tt, c) * flen, flen, n, inner, x, zero_border);
                acc = c ? acc + e : e;
            }
            out_o[xi] = acc;
        }
    }
}

/* One element of conv_axis_bwd (see there); line = &v_out[o, 0, k]. */
inline float v_conv_elem(__global const float *line, __global const float *f, int flen, int n, int inner,
                         int y) {
    const int R = flen / 2;
    float acc = 0.0f;
    if (y > R && y < n - 1 - R) {
        /* interior: m = y is the only padded position in [-R, n - 1 + R] that reflects onto y,
         * and every x = y + i - R lies in [0, n) */
        for (int i = 0; i < flen; ++i)
            acc += f[i] * line[(size_t)(y + i - R) * inner];
    } else {
        const int lo = -R, hi = n - 1 + R;
        if (n == 1) {
            for (int m = lo; m <= hi; ++m)
                for (int i = 0; i < flen; ++i) {
                    const int x = m + i - R;
                    if (x >= 0 && x < n) acc += f[i] * line[(size_t)x * inner];
                }
        } else {
            const int P = 2 * (n - 1);
            const int nres = (y == 0 || y == n - 1) ? 1 : 2;
            for (int s = 0; s < nres; ++s) {
                const int r = (s == 0) ? y : P - y;      /* residue of m modulo P */
                int m = r - ((r - lo) / P) * P;          /* smallest m >= lo with m = r (mod P) */
                for (; m <= hi; m += P)
                    for (int i = 0; i < flen; ++i) {
                        const int x = m + i - R;
                        if (x >= 0 && x < n) acc += f[i] * line[(size_t)x * inner];
                    }
            }
        }
    }
    return acc;
}

/* v_conv_elem for the 8 consecutive flat elements yi .. yi + 7 of a line (line = &v_out[o, 0, 0])
 * that may span positions (a row pass: inner < 8), for an axis longer than the filter (n > 2 R + 1:
 * a position y has the padded position y itself and at most one reflection of it, -y when
 * y <= R, 2 (n - 1) - y when y >= n - 1 - R).  The same terms in the same order as v_conv_elem (y's
 * own taps, then the reflection's), the values gathered; a term that v_conv_elem skips adds 0.
 * The per-lane choices are selects (sel_i8, sel_f8, bit operations): written as vector ?: this
 * function computed wrong values on Oclgrind 21.10 (right ones on PoCL). */
inline float8 v_conv_gather8(__global const float *line, __global const float *f, int flen, int n, int inner,
                             int yi) {
    const int R = flen / 2;
    const int8 e = (int8)(yi) + (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    const int8 y = e / inner;
    const int8 k = e - y * inner;
    const int8 m2 = sel_i8((int8)(2 * (n - 1)) - y, -y, y <= (int8)(R));     /* the reflection */
    const int8 has2 = (y != (int8)(0)) & (y != (int8)(n - 1)) & ((y <= (int8)(R)) | (y >= (int8)(n - 1 - R)));
    float8 acc = (float8)(0.0f);
    for (int pass = 0; pass < 2; ++pass) {
        const int8 m = pass ? m2 : y;
        const int8 on = pass ? has2 : (int8)(-1);
        for (int i = 0; i < flen; ++i) {
            const int8 x = m + (int8)(i - R);
            const int8 use = on & (x >= (int8)(0)) & (x < (int8)(n));
            const int8 src = sel_i8((int8)(0), x, use) * inner + k;
            float8 v = gather8(line, src);
            v = sel_f8((float8)(0.0f), v, use);
            acc += f[i] * v;
        }
    }
    return acc;
}

/* Adjoint of conv_axis, with the same term table read the other way: output slot t of conv_axis_bwd
 * is the sum over its terms (s, g) of the adjoint of convolving with f[g], applied to v_out slot s.
 * For one term: v_in[o, y, k] (+)= sum over padded positions m in [-R, n - 1 + R] with
 * reflect(m) = y of sum_i f[i] v_out[o, m + i - R, k] (terms with m + i - R outside [0, n)
 * dropped).  The positions m that reflect onto y are y + j P and -y + j P, P = 2 (n - 1).
 * accumulate != 0 adds the sum to v_in instead of overwriting it.  Work-item (u, o, t) computes
 * CONV_RUN consecutive flat elements of line o of slot t, as in conv_axis. */
__kernel void conv_axis_bwd(__global const float *v_out, __global float *v_in,
                          __global const float *f, const int flen,
                          const int outer, const int n, const int inner, const int accumulate,
                          __global const int *terms, const int term_stride) {
    const int yi0 = get_global_id(0) * CONV_RUN;    /* first y * inner + k of this work-item */
    const int o = get_global_id(1);
    const int t = get_global_id(2);
    const int len = n * inner;
    if (yi0 >= len || o >= outer) return;
    const int R = flen / 2;
    const size_t slot = (size_t)outer * len;
    __global const int *tt = terms + t * term_stride;
    const int nterm = tt[0];
    __global float *vi = v_in + t * slot + (size_t)o * len;
    /* yi0 / inner > R and (yi0 + CONV_RUN - 1) / inner < n - 1 - R, without the divisions */
    if (yi0 + CONV_RUN <= len && yi0 >= (R + 1) * inner && yi0 + CONV_RUN - 1 < (n - 1 - R) * inner) {
        /* interior run: element yi reads vo[yi + (i - R) inner] for tap i */
#if CONV_RUN == 16
        float8 lo = (float8)(0.0f), hi = (float8)(0.0f);
        for (int c = 0; c < nterm; ++c) {
            float8 a, b;
            conv_run16(v_out + TERM_SRC(tt, c) * slot + (size_t)o * len + yi0, f + TERM_FILTER(tt, c) * flen,
                       flen, inner, &a, &b);
            lo = c ? lo + a : a;
            hi = c ? hi + b : b;
        }
        if (accumulate) {
            lo += load8(vi + yi0);
            hi += load8(vi + yi0 + 8);
        }
        store8(vi + yi0, lo);
        store8(vi + yi0 + 8, hi);
#else
        float8 acc = (float8)(0.0f);
        for (int c = 0; c < nterm; ++c) {
            const float8 a = conv_run8(v_out + TERM_SRC(tt, c) * slot + (size_t)o * len + yi0,
                                       f + TERM_FILTER(tt, c) * flen, flen, inner);
            acc = c ? acc + a : a;
        }
        if (accumulate) acc += load8(vi + yi0);
        store8(vi + yi0, acc);
#endif
    } else if (yi0 - (yi0 / inner) * inner + CONV_RUN <= inner) {
        /* a border run within one position y (a column pass): 8 elements at a time */
        const int y = yi0 / inner, k0 = yi0 - y * inner;
        for (int h = 0; h < CONV_RUN; h += 8) {
            float8 acc = (float8)(0.0f);
            for (int c = 0; c < nterm; ++c) {
                const float8 e = v_conv_elem8(v_out + TERM_SRC(tt, c) * slot + (size_t)o * len + k0 + h,
                                              f + TERM_FILTER(tt, c) * flen, flen, n, inner, y);
                acc = c ? acc + e : e;
            }
            if (accumulate) acc += load8(vi + yi0 + h);
            store8(vi + yi0 + h, acc);
        }
    } else if (yi0 + CONV_RUN <= len && n > 2 * R + 1) {
        /* a border run across positions (a row pass): 8 elements at a time, gathered */
        for (int h = 0; h < CONV_RUN; h += 8) {
            float8 acc = (float8)(0.0f);
            for (int c = 0; c < nterm; ++c) {
                const float8 e = v_conv_gather8(v_out + TERM_SRC(tt, c) * slot + (size_t)o * len,
                                                f + TERM_FILTER(tt, c) * flen, flen, n, inner, yi0 + h);
                acc = c ? acc + e : e;
            }
            if (accumulate) acc += load8(vi + yi0 + h);
            store8(vi + yi0 + h, acc);
        }
    } else {
        const int end = yi0 + CONV_RUN < len ? yi0 + CONV_RUN : len;
        for (int yi = yi0; yi < end; ++yi) {
            const int y = yi / inner;
            float acc = 0.0f;
            for (int c = 0; c < nterm; ++c) {
                const float e = v_conv_elem(v_out + TERM_SRC(tt, c) * slot + (size_t)o * len + (yi - y * inner),
                                            f + TERM_FILTER(tt, c) * flen, flen, n, inner, y);
                acc = c ? acc + e : e;
            }
            if (accumulate) acc += vi[yi];
            vi[yi] = acc;
        }
    }
}

/* Row passes staged through local memory (conv_axis_rows, conv_axis_rows_bwd).  Along an image's
 * rows (inner < CONV_RUN: a run spans positions) the border runs of conv_axis / conv_axis_bwd
 * gather every tap with per-lane reflection (conv_gather8, v_conv_gather8): about 4 of a 320-pixel
 * row's 60 runs, yet more than half of the pass's time.  Here one work-group takes one line of one
 * output slot: it first copies its terms' input lines into local memory with the border already
 * applied (conv_axis_rows: the reflected or zero samples R positions past each end; the adjoint:
 * 2 R zeros past each end), after which every run of the line is an interior run of 8-wide loads.
 * The values, the taps and their order are those of the unstaged kernels (a tap outside a
 * zero-border line or an adjoint's line adds f 0, as the gathered paths do): the same results. */

/* Copies the input line of each of the group's nterm terms into l_lines (term c at c * plen):
 * staged position e / inner - pad of the line, element k = e % inner, for e in [0, plen); a
 * position outside [0, n) reads its reflection (reflect != 0) or 0.  One more float at
 * nterm * plen holds 0 (conv_axis_rows_bwd points its lanes without a reflection there).  Ends
 * with the barrier after which the staged lines may be read. */
inline void stage_lines(__global const float *in, size_t slot, size_t line_off, __global const int *tt,
                        int nterm, int n, int inner, int pad, int reflect, __local float *l_lines) {
    const int lid = get_local_id(0), L = get_local_size(0);
    const int len = n * inner, plen = (n + 2 * pad) * inner;
    for (int c = 0; c < nterm; ++c) {
        __global const float *line = in + TERM_SRC(tt, c) * slot + line_off;
        __local float *dst = l_lines + c * plen + pad * inner;   /* position 0 */
        for (int e = lid * 8; e < len; e += L * 8) {             /* the line itself, 8 at a time */
            if (e + 8 <= len) {
                const float8 v = load8(line + e);
                dst[e] = v.s0; dst[e + 1] = v.s1; dst[e + 2] = v.s2; dst[e + 3] = v.s3;
                dst[e + 4] = v.s4; dst[e + 5] = v.s5; dst[e + 6] = v.s6; dst[e + 7] = v.s7;
            } else {
                for (int j = e; j < len; ++j) dst[j] = line[j];
            }
        }
        for (int b = lid; b < 2 * pad; b += L) {                 /* the pad positions past each end */
            const int m = b < pad ? b - pad : n + b - pad;
            const int src = reflect ? reflect_idx(m, n) : 0;
            for (int k = 0; k < inner; ++k) dst[m * inner + k] = reflect ? line[src * inner + k] : 0.0f;
        }
    }
    if (lid == 0) l_lines[nterm * plen] = 0.0f;
    barrier(CLK_LOCAL_MEM_FENCE);
}

/* 8 floats to local memory (store8 of common.h for a line kept in local memory). */
inline void store8_l(__local float *p, float8 v) {
    p[0] = v.s0; p[1] = v.s1; p[2] = v.s2; p[3] = v.s3;
    p[4] = v.s4; p[5] = v.s5; p[6] = v.s6; p[7] = v.s7;
}

/* rows_fwd_runs<S>: the runs of one line of conv_axis_rows's output slot tt (n * inner elements at
 * out_o) from the group's staged lines (l_lines: term c at c * (n + 2 R) * inner, R samples past
 * each end): work-item l of L takes the runs l, l + L, ...  Written once for an output line in
 * global memory (S empty: conv_axis_rows) and in local memory (S = _l: conv_resample_rows). */
#if CONV_RUN == 16
#define ROWS_FWD_VECTOR_RUN(STORE)                                                                  \
            float8 lo = (float8)(0.0f), hi = (float8)(0.0f);                                        \
            for (int c = 0; c < nterm; ++c) {                                                       \
                float8 a, b;                                                                        \
                conv_run16_l(l_lines + c * plen + R * inner + xi0, f + TERM_FILTER(tt, c) * flen, flen, \
                             -inner, &a, &b);                                                       \
                lo = c ? lo + a : a;                                                                \
                hi = c ? hi + b : b;                                                                \
            }                                                                                       \
            STORE(out_o + xi0, lo);                                                                 \
            STORE(out_o + xi0 + 8, hi);
#else
#define ROWS_FWD_VECTOR_RUN(STORE)                                                                  \
            float8 acc = (float8)(0.0f);                                                            \
            for (int c = 0; c < nterm; ++c) {                                                       \
                const float8 a = conv_run8_l(l_lines + c * plen + R * inner + xi0,                  \
                                             f + TERM_FILTER(tt, c) * flen, flen, -inner);          \
                acc = c ? acc + a : a;                                                              \
            }                                                                                       \
            STORE(out_o + xi0, acc);
#endif
#define ROWS_FWD_RUNS(S, AS, STORE)                                                                 \
inline void rows_fwd_runs##S(AS float *out_o, __global const float *f, int flen, int n, int inner, \
                             __global const int *tt, __local const float *l_lines) {                \
    const int lid = get_local_id(0), L = get_local_size(0);                                         \
    const int R = flen / 2;                                                                         \
    const int len = n * inner, plen = (n + 2 * R) * inner;                                          \
    const int nterm = tt[0];                                                                        \
    for (int xi0 = lid * CONV_RUN; xi0 < len; xi0 += L * CONV_RUN) {                                \
        /* element xi reads staged[xi + R inner + (R - i) inner] for tap i */                       \
        if (xi0 + CONV_RUN <= len) {                                                                \
            ROWS_FWD_VECTOR_RUN(STORE)                                                              \
        } else {                                                                                    \
            for (int xi = xi0; xi < len; ++xi) {                                                    \
                float acc = 0.0f;                                                                   \
                for (int c = 0; c < nterm; ++c) {                                                   \
                    __local const float *src = l_lines + c * plen + R * inner + xi;                 \
                    __global const float *fc = f + TERM_FILTER(tt, c) * flen;                       \
                    float e = 0.0f;                                                                 \
                    for (int i = 0; i < flen; ++i) e += fc[i] * src[(R - i) * inner];               \
                    acc = c ? acc + e : e;                                                          \
                }                                                                                   \
                out_o[xi] = acc;                                                                    \
            }                                                                                       \
        }                                                                                           \
    }                                                                                               \
}
ROWS_FWD_RUNS(, __global, store8)
ROWS_FWD_RUNS(_l, __local, store8_l)

/* conv_axis for a row pass: the same arguments, and l_lines [max terms * (n + 2 R) * inner + 1]
 * floats of local memory.  Range (L, outer, slots), work-groups (L, 1, 1): work-item l of the
 * group of (o, t) computes the runs l, l + L, ... of line o of output slot t. */
__kernel void conv_axis_rows(__global const float *in, __global float *out,
                             __global const float *f, const int flen,
                             const int outer, const int n, const int inner, const int zero_border,
                             __global const int *terms, const int term_stride, __local float *l_lines) {
    const int o = get_global_id(1);
    const int t = get_global_id(2);
    const size_t slot = (size_t)outer * n * inner;
    __global const int *tt = terms + t * term_stride;
    stage_lines(in, slot, (size_t)o * n * inner, tt, tt[0], n, inner, flen / 2, !zero_border, l_lines);
    rows_fwd_runs(out + t * slot + (size_t)o * n * inner, f, flen, n, inner, tt, l_lines);
}

/* The reflection pass of conv_axis_rows_bwd for the 8 flat elements yi .. yi + 7 of the line: acc
 * continued with the taps of each lane's reflected position (-y near the start, 2 (n - 1) - y near
 * the end), in the order of v_conv_gather8's second pass; lanes without one read the staged zero
 * (the gathered path adds f 0 there too).  src: the staged line (2 R zeros past each end), zero:
 * the offset of the staged zero. */
inline float8 v_reflect_pass8(float8 acc, __local const float *src, __global const float *f, int flen, int n,
                              int inner, int yi, int zero) {
    const int R = flen / 2;
    const int8 e = (int8)(yi) + (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    const int8 y = e / inner;
    const int8 k = e - y * inner;
    const int8 m2 = sel_i8((int8)(2 * (n - 1)) - y, -y, y <= (int8)(R));
    const int8 has2 = (y != (int8)(0)) & (y != (int8)(n - 1)) & ((y <= (int8)(R)) | (y >= (int8)(n - 1 - R)));
    /* staged index of tap 0: position m2 - R, 2 R zeros before position 0 */
    const int8 base = sel_i8((int8)(zero), (m2 + (int8)(R)) * inner + k, has2);
    const int8 step = sel_i8((int8)(0), (int8)(inner), has2);
    for (int i = 0; i < flen; ++i) {
        const int8 ix = base + step * (int8)(i);
        const float8 v = (float8)(src[ix.s0], src[ix.s1], src[ix.s2], src[ix.s3],
                                  src[ix.s4], src[ix.s5], src[ix.s6], src[ix.s7]);
        acc += f[i] * v;
    }
    return acc;
}

/* The runs of one line of conv_axis_rows_bwd's output slot tt (n * inner elements at vi) from the
 * group's staged lines (l_lines: term c at c * (n + 4 R) * inner, 2 R zeros past each end of each,
 * and the staged zero after the last): work-item l of L takes the runs l, l + L, ...  Each run's
 * own taps read the staged line as interior runs do; the runs that hold a border position (y <= R
 * or y >= n - 1 - R) then add their reflections' taps (v_reflect_pass8). */
inline void rows_bwd_runs(__global float *vi, __global const float *f, int flen, int n, int inner,
                          int accumulate, __global const int *tt, __local const float *l_lines) {
    const int lid = get_local_id(0), L = get_local_size(0);
    const int R = flen / 2;
    const int len = n * inner, plen = (n + 4 * R) * inner;
    const int nterm = tt[0];
    const int zero = nterm * plen;
    for (int yi0 = lid * CONV_RUN; yi0 < len; yi0 += L * CONV_RUN) {
        /* element yi reads staged[yi + 2 R inner + (i - R) inner] for tap i */
        if (yi0 + CONV_RUN <= len) {
            const int border = yi0 < (R + 1) * inner || yi0 + CONV_RUN - 1 >= (n - 1 - R) * inner;
            for (int h = 0; h < CONV_RUN; h += 8) {
                float8 acc = (float8)(0.0f);
                for (int c = 0; c < nterm; ++c) {
                    __local const float *line = l_lines + c * plen;
                    __global const float *fc = f + TERM_FILTER(tt, c) * flen;
                    float8 e = conv_run8_l(line + 2 * R * inner + yi0 + h, fc, flen, inner);
                    if (border) e = v_reflect_pass8(e, line, fc, flen, n, inner, yi0 + h, zero - c * plen);
                    acc = c ? acc + e : e;
                }
                if (accumulate) acc += load8(vi + yi0 + h);
                store8(vi + yi0 + h, acc);
            }
        } else {
            for (int yi = yi0; yi < len; ++yi) {
                const int y = yi / inner, k = yi - y * inner;
                float acc = 0.0f;
                for (int c = 0; c < nterm; ++c) {
                    __local const float *line = l_lines + c * plen;
                    __global const float *fc = f + TERM_FILTER(tt, c) * flen;
                    float e = 0.0f;
                    for (int i = 0; i < flen; ++i) e += fc[i] * line[yi + 2 * R * inner + (i - R) * inner];
                    const int has2 = y != 0 && y != n - 1 && (y <= R || y >= n - 1 - R);
                    const int m2 = y <= R ? -y : 2 * (n - 1) - y;
                    for (int i = 0; i < flen; ++i)
                        e += fc[i] * (has2 ? line[(m2 + R + i) * inner + k] : 0.0f);
                    acc = c ? acc + e : e;
                }
                if (accumulate) acc += vi[yi];
                vi[yi] = acc;
            }
        }
    }
}

/* conv_axis_bwd for a row pass of a line longer than the filter (n > 2 R + 1: at most one
 * reflection per position): the same arguments, and l_lines [max terms * (n + 4 R) * inner + 1]
 * floats of local memory; range and work-groups as conv_axis_rows. */
__kernel void conv_axis_rows_bwd(__global const float *v_out, __global float *v_in,
                                 __global const float *f, const int flen,
                                 const int outer, const int n, const int inner, const int accumulate,
                                 __global const int *terms, const int term_stride, __local float *l_lines) {
    const int o = get_global_id(1);
    const int t = get_global_id(2);
    const size_t slot = (size_t)outer * n * inner;
    __global const int *tt = terms + t * term_stride;
    stage_lines(v_out, slot, (size_t)o * n * inner, tt, tt[0], n, inner, 2 * (flen / 2), 0, l_lines);
    rows_bwd_runs(v_in + t * slot + (size_t)o * n * inner, f, flen, n, inner, accumulate, tt, l_lines);
}

/* The resampling kernels also compute RS_RUN = 8 consecutive flat elements (j * inner + k) of a
 * line per work-item: one integer division by inner per run instead of two per element (a scalar
 * idiv each on PoCL), and, when the run stays in one j (the column passes, inner = W C), one
 * 8-wide load per source sample.  Same terms in the same order as one element per work-item. */
#define RS_RUN 8
/* The most source samples j with |j p - i q| < q for one i: the adjoint's fixed loop count. */
#define RS_JMAX ((2 * RQ - 2) / RP + 1)

/* Output sample j of the resampling interpolates input samples i0 and i0 + 1 with weight r / q:
 * j p = i0 q + r, 0 <= r < q.  Returns i0, sets *r. */
inline int rs_source(int j, int *r) {
    const int i0 = (j * RP) / RQ;
    *r = j * RP - i0 * RQ;
    return i0;
}

/* The output samples j that input sample i feeds (|j p - i q| < q), clamped to [0, n_out). */
inline int2 rs_targets(int i, int n_out) {
    const int num_lo = (i - 1) * RQ + 1;
    const int jlo = num_lo > 0 ? (num_lo + RP - 1) / RP : 0;
    const int jhi = ((i + 1) * RQ - 1) / RP;
    return (int2)(jlo, jhi < n_out - 1 ? jhi : n_out - 1);
}

/* The weight of output sample j in input sample i's adjoint, 0 when j is not one of its targets:
 * max(0, 1 - |j p - i q| / q).  |j p - i q| in float (exact for these small integers): the
 * integer abs is an out-of-line call on PoCL, and Oclgrind lacks the llvm.abs intrinsic it becomes;
 * the float's |.| as a bit operation (fabs is an out-of-line call on PoCL too; the same value). */
#define RS_ABS(x) as_float(as_int(x) & 0x7fffffff)
#define RS_WEIGHT_OK(j, i) (RS_ABS((float)((j) * RP - (i) * RQ)) < (float)RQ)
#define RS_WEIGHT(j, i) (((float)RQ - RS_ABS((float)((j) * RP - (i) * RQ))) / (float)RQ)

/* Rational resampling by a = p / q = RP / RQ (linear interpolation at n_out * p / q):
 * out[o, j, k] = ((q - r) in[o, i0, k] + r in[o, i0 + 1, k]) / q,  j p = i0 q + r, 0 <= r < q.
 * in: [outer, n_in, inner]; out: [outer, n_out, inner], n_out = (n_in - 1) q / p + 1.
 * Work-item (t, o) computes the flat elements t * RS_RUN ... t * RS_RUN + RS_RUN - 1 of line o. */
__kernel void resample_axis(__global const float *in, __global float *out,
                            const int outer, const int n_in, const int n_out, const int inner) {
    const int o = get_global_id(1);
    const int xi0 = get_global_id(0) * RS_RUN;  /* first j * inner + k of this work-item */
    if (xi0 >= n_out * inner || o >= outer) return;
    __global const float *in_o = in + (size_t)o * n_in * inner;
    __global float *out_o = out + (size_t)o * n_out * inner;
    int j = xi0 / inner, r;
    int k = xi0 - j * inner;
    const int end = min(xi0 + RS_RUN, n_out * inner);
    if (end - xi0 == RS_RUN && k + RS_RUN <= inner) {   /* one j for the whole run */
        const int i0 = rs_source(j, &r);
        float8 v = load8(in_o + (size_t)i0 * inner + k);
        if (r > 0) {
            const float w = (float)r / (float)RQ;
            v = (1.0f - w) * v + w * load8(in_o + (size_t)(i0 + 1) * inner + k);
        }
        store8(out_o + xi0, v);
        return;
    }
    for (int xi = xi0; xi < end; ++xi) {
        const int i0 = rs_source(j, &r);
        __global const float *line = in_o + k;
        float v = line[(size_t)i0 * inner];
        if (r > 0) {  /* then i0 + 1 <= n_in - 1 because j p / q <= n_in - 1 */
            const float w = (float)r / (float)RQ;
            v = (1.0f - w) * v + w * line[(size_t)(i0 + 1) * inner];
        }
        out_o[xi] = v;
        if (++k == inner) { k = 0; ++j; }
    }
}

/* Adjoint of resample_axis: v_in[o, i, k] (+)= sum_j max(0, 1 - |j p - i q| / q) v_out[o, j, k],
 * over the j with |j p - i q| < q, i.e. ceil(((i - 1) q + 1) / p) <= j <= floor(((i + 1) q - 1) / p)
 * (at most RS_JMAX of them, in increasing j).  Work-item (t, o): RS_RUN flat elements i * inner + k. */
__kernel void resample_axis_bwd(__global const float *v_out, __global float *v_in,
                              const int outer, const int n_in, const int n_out, const int inner,
                              const int accumulate) {
    const int o = get_global_id(1);
    const int yi0 = get_global_id(0) * RS_RUN;  /* first i * inner + k of this work-item */
    const int len = n_in * inner;
    if (yi0 >= len || o >= outer) return;
    __global const float *vo = v_out + (size_t)o * n_out * inner;
    __global float *vi = v_in + (size_t)o * len;
    int i = yi0 / inner;
    int k = yi0 - i * inner;
    if (yi0 + RS_RUN <= len && k + RS_RUN <= inner) {   /* one i for the whole run */
        const int2 jr = rs_targets(i, n_out);
        float8 acc = (float8)(0.0f);
        for (int t = 0; t < RS_JMAX; ++t) {
            const int j = jr.s0 + t;
            if (j > jr.s1) break;
            if (RS_WEIGHT_OK(j, i)) acc += RS_WEIGHT(j, i) * load8(vo + (size_t)j * inner + k);
        }
        if (accumulate) acc += load8(vi + yi0);
        store8(vi + yi0, acc);
        return;
    }
    const int end = yi0 + RS_RUN < len ? yi0 + RS_RUN : len;
    for (int yi = yi0; yi < end; ++yi) {
        const int2 jr = rs_targets(i, n_out);
        float acc = 0.0f;
        for (int t = 0; t < RS_JMAX; ++t) {
            const int j = jr.s0 + t;
            if (j > jr.s1) break;
            if (RS_WEIGHT_OK(j, i)) acc += RS_WEIGHT(j, i) * vo[(size_t)j * inner + k];
        }
        if (accumulate) acc += vi[yi];
        vi[yi] = acc;
        if (++k == inner) { k = 0; ++i; }
    }
}

/* resample_axis and resample_axis_bwd for a short inner axis (the row passes of an image,
 * inner = C < RS_RUN): work-item (u, o) computes the inner elements of RS_ROW_POS consecutive
 * positions of line o, from position u * RS_ROW_POS on (no division by inner at all; one position
 * per work-item left PoCL's per-work-item cost larger than the work).  An image's 3 channels take
 * a copy of the loops with inner the constant 3, which the compiler unrolls.  The same terms in
 * the same order as the kernels above. */
#define RS_ROW_POS 8
#define RS_ROWS_3(BODY) if (inner == 3) { BODY(3) } else { BODY(inner) }

/* out[o, j, :] for output position j, from the line in_o (inner = INNER) */
#define RS_ROW_OUT(INNER, in_o, out_o, j)                                                     \
    {                                                                                         \
        int r;                                                                                \
        const int i0 = rs_source(j, &r);                                                      \
        const float w = (float)r / (float)RQ;                                                 \
        for (int k = 0; k < (INNER); ++k) {                                                   \
            float v = (in_o)[i0 * (INNER) + k];                                               \
            if (r > 0) v = (1.0f - w) * v + w * (in_o)[(i0 + 1) * (INNER) + k];               \
            (out_o)[(j) * (INNER) + k] = v;                                                   \
        }                                                                                     \
    }

/* acc = the adjoint at input position i, element k, from the line vo (inner = INNER) */
#define RS_ROW_ADJ(INNER, vo, i, k, acc)                                                      \
    {                                                                                         \
        const int2 jr = rs_targets(i, n_out);                                                 \
        for (int u = 0; u < RS_JMAX; ++u) {                                                   \
            const int j = jr.s0 + u;                                                          \
            if (j > jr.s1) break;                                                             \
            if (RS_WEIGHT_OK(j, i)) acc += RS_WEIGHT(j, i) * (vo)[(size_t)j * (INNER) + k];   \
        }                                                                                     \
    }

__kernel void resample_axis_rows(__global const float *in, __global float *out,
                                 const int outer, const int n_in, const int n_out, const int inner) {
    const int j0 = get_global_id(0) * RS_ROW_POS;
    const int o = get_global_id(1);
    if (j0 >= n_out || o >= outer) return;
    const int j1 = j0 + RS_ROW_POS < n_out ? j0 + RS_ROW_POS : n_out;
    __global const float *in_o = in + (size_t)o * n_in * inner;
    __global float *out_o = out + (size_t)o * n_out * inner;
#define RS_FWD(INNER) for (int j = j0; j < j1; ++j) RS_ROW_OUT(INNER, in_o, out_o, j)
    RS_ROWS_3(RS_FWD)
#undef RS_FWD
}

__kernel void resample_axis_bwd_rows(__global const float *v_out, __global float *v_in,
                                     const int outer, const int n_in, const int n_out, const int inner,
                                     const int accumulate) {
    const int i0 = get_global_id(0) * RS_ROW_POS;
    const int o = get_global_id(1);
    if (i0 >= n_in || o >= outer) return;
    const int i1 = i0 + RS_ROW_POS < n_in ? i0 + RS_ROW_POS : n_in;
    __global const float *vo = v_out + (size_t)o * n_out * inner;
    __global float *vi = v_in + (size_t)o * n_in * inner;
#define RS_BWD(INNER)                                                                         \
    for (int i = i0; i < i1; ++i)                                                             \
        for (int k = 0; k < (INNER); ++k) {                                                   \
            float acc = 0.0f;                                                                 \
            RS_ROW_ADJ(INNER, vo, i, k, acc)                                                  \
            if (accumulate) acc += vi[i * (INNER) + k];                                       \
            vi[i * (INNER) + k] = acc;                                                        \
        }
    RS_ROWS_3(RS_BWD)
#undef RS_BWD
}

/* The adjoint of a row pass followed by the row resampling (decompose_level_stack's rows), in one
 * launch: conv_axis_rows_bwd whose staged lines are made by resample_axis_bwd_rows from the
 * resampled cotangents v_out [S, outer, n_out, inner] (line o of input slot s), instead of read
 * from an array that resample_axis_bwd_rows would have written.  The same values in the same
 * order: the same bits as the two launches.  v_in: [T, outer, n, inner] (+= with accumulate);
 * n > 2 R + 1. */
__kernel void resample_conv_rows_bwd(__global const float *v_out, __global float *v_in,
                                     __global const float *f, const int flen,
                                     const int outer, const int n, const int n_out, const int inner,
                                     const int accumulate, __global const int *terms, const int term_stride,
                                     __local float *l_lines) {
    const int o = get_global_id(1);
    const int t = get_global_id(2);
    const int lid = get_local_id(0), L = get_local_size(0);
    const int R = flen / 2;
    const int plen = (n + 4 * R) * inner;
    __global const int *tt = terms + t * term_stride;
    const int nterm = tt[0];
    for (int c = 0; c < nterm; ++c) {
        __global const float *vo = v_out + (TERM_SRC(tt, c) * (size_t)outer + o) * n_out * inner;
        __local float *dst = l_lines + c * plen + 2 * R * inner;   /* position 0 */
#define RS_STAGE(INNER)                                            /* resample_axis_bwd_rows */ \
        for (int i = lid; i < n; i += L)                                                      \
            for (int k = 0; k < (INNER); ++k) {                                               \
                float acc = 0.0f;                                                             \
                RS_ROW_ADJ(INNER, vo, i, k, acc)                                              \
                dst[i * (INNER) + k] = acc;                                                   \
            }
        RS_ROWS_3(RS_STAGE)
#undef RS_STAGE
        for (int b = lid; b < 4 * R * inner; b += L)               /* 2 R zeros past each end */
            dst[b < 2 * R * inner ? b - 2 * R * inner : n * inner + b - 2 * R * inner] = 0.0f;
    }
    if (lid == 0) l_lines[nterm * plen] = 0.0f;
    barrier(CLK_LOCAL_MEM_FENCE);
    rows_bwd_runs(v_in + (t * (size_t)outer + o) * n * inner, f, flen, n, inner, accumulate, tt, l_lines);
}

/* A row pass followed by the row resampling (decompose_level_stack's rows) in one launch:
 * conv_axis_rows (reflect border) whose output line stays in local memory (l_conv [n inner]), then
 * resample_axis_rows from it into out [T, outer, n_out, inner].  The same values in the same order:
 * the same bits as the two launches.  l_lines as conv_axis_rows. */
__kernel void conv_resample_rows(__global const float *in, __global float *out,
                                 __global const float *f, const int flen,
                                 const int outer, const int n, const int n_out, const int inner,
                                 __global const int *terms, const int term_stride,
                                 __local float *l_lines, __local float *l_conv) {
    const int o = get_global_id(1);
    const int t = get_global_id(2);
    const int lid = get_local_id(0), L = get_local_size(0);
    __global const int *tt = terms + t * term_stride;
    stage_lines(in, (size_t)outer * n * inner, (size_t)o * n * inner, tt, tt[0], n, inner, flen / 2, 1, l_lines);
    rows_fwd_runs_l(l_conv, f, flen, n, inner, tt, l_lines);
    barrier(CLK_LOCAL_MEM_FENCE);
    __global float *out_o = out + (t * (size_t)outer + o) * n_out * inner;
#define RS_FWD(INNER) for (int j = lid; j < n_out; j += L) RS_ROW_OUT(INNER, l_conv, out_o, j)
    RS_ROWS_3(RS_FWD)
#undef RS_FWD
}

/* d[p, c] = (a[p, c] - b[p, c]) * (has_mask ? mask[p] : 1).  a, b, d: [npix, C]; mask: [npix] */
__kernel void masked_diff(__global const float *a, __global const float *b,
                          __global const float *mask, __global float *d,
                          const int npix, const int C, const int has_mask) {
    const int gid = get_global_id(0);
    if (gid >= npix * C) return;
    float v = a[gid] - b[gid];
    if (has_mask) v *= mask[gid / C];
    d[gid] = v;
}

/* x[i] *= (has_mask ? mask[i / C] : 1) * s, in place.  x: [npix, C] */
__kernel void scale_masked(__global float *x, __global const float *mask, const float s,
                           const int npix, const int C, const int has_mask) {
    const int gid = get_global_id(0);
    if (gid >= npix * C) return;
    float v = x[gid] * s;
    if (has_mask) v *= mask[gid / C];
    x[gid] = v;
}

/* For band b = get_global_id(1) of the stack x [bands, m]: work-item u sums the squares of its
 * RED_CHUNK consecutive elements into partial[base + b * chunks + u] (chunks = the global size along
 * dimension 0) and scales them in place by s_b (s0 .. s3: at most four bands), each element read
 * once and then written; the partial sums are those of the unscaled band, added up by the host.
 * (No work-group reduction: on PoCL a barrier-synchronised tree took twenty times as long.)
 * RED_CHUNK, a multiple of 8, is a build option (endowave_cl/wavelet/ops.py); builds of this file
 * without it leave the kernel out. */
#ifdef RED_CHUNK
__kernel void sumsq_scale(__global float *x, const int m, __global float *partial, const int base,
                          const float s0, const float s1, const float s2, const float s3) {
    const int u = get_global_id(0);
    const int b = get_global_id(1);
    const int chunks = get_global_size(0);
    const float s = b == 0 ? s0 : b == 1 ? s1 : b == 2 ? s2 : s3;
    __global float *xb = x + (size_t)b * m;
    const int i0 = u * RED_CHUNK;
    float acc = 0.0f;
    if (i0 + RED_CHUNK <= m) {
        float8 a = (float8)(0.0f);
        for (int k = 0; k < RED_CHUNK; k += 8) {
            const float8 v = load8(xb + i0 + k);
            a += v * v;
            store8(xb + i0 + k, v * s);
        }
        acc = ((a.s0 + a.s1) + (a.s2 + a.s3)) + ((a.s4 + a.s5) + (a.s6 + a.s7));
    } else {
        for (int i = i0; i < m; ++i) {
            const float v = xb[i];
            acc += v * v;
            xb[i] = v * s;
        }
    }
    partial[base + b * chunks + u] = acc;
}
#endif
