/* Rational-wavelet transform kernels (OpenCL C 1.2): separable convolution along one axis,
 * rational resampling along one axis, their adjoints, and the small element-wise and reduction
 * kernels of the wavelet loss.  Host side and conventions: endowave_cl/wavelet/ops.py and
 * endowave_cl/wavelet/filters.py (docs/WAVELET.md).
 *
 * Axis-generic layout: a contiguous array is viewed as [outer, n, inner] and the operation runs
 * along the middle axis.  For a channel-last image [H, W, C]: rows (along W) are
 * outer = H, n = W, inner = C; columns (along H) are outer = 1, n = H, inner = W * C.
 * One work-item per output element, 2-D global range: dimension 0 = x * inner + k (contiguous in
 * memory), dimension 1 = o; the element's flat index is o * n * inner + x * inner + k.
 */
#include "common.h"

/* Whole-sample symmetric reflection of position m into [0, n): -1 -> 1, n -> n - 2, repeated. */
inline int reflect_idx(int m, int n) {
    if (n == 1) return 0;
    int period = 2 * (n - 1);
    int r = m % period;
    if (r < 0) r += period;
    return r < n ? r : period - r;
}

/* out[o, x, k] = sum_i f[i] in[o, reflect(x - (i - R)), k], R = flen / 2 (flen odd).
 * in, out: [outer, n, inner]; f: [flen] */
__kernel void conv_axis(__global const float *in, __global float *out,
                        __global const float *f, const int flen,
                        const int outer, const int n, const int inner) {
    const int xi = get_global_id(0);            /* x * inner + k */
    const int o = get_global_id(1);
    if (xi >= n * inner || o >= outer) return;
    const int k = xi % inner;
    const int x = xi / inner;
    const size_t gid = (size_t)o * n * inner + xi;
    const int R = flen / 2;
    __global const float *line = in + (size_t)o * n * inner + k;
    float acc = 0.0f;
    if (x - R >= 0 && x + R < n) {          /* interior: no reflection needed */
        for (int i = 0; i < flen; ++i)
            acc += f[i] * line[(size_t)(x - i + R) * inner];
    } else {
        for (int i = 0; i < flen; ++i)
            acc += f[i] * line[(size_t)reflect_idx(x - i + R, n) * inner];
    }
    out[gid] = acc;
}

/* Adjoint of conv_axis.  v_in[o, y, k] (+)= sum over padded positions m in [-R, n - 1 + R] with
 * reflect(m) = y of sum_i f[i] v_out[o, m + i - R, k] (terms with m + i - R outside [0, n)
 * dropped).  The positions m that reflect onto y are y + j P and -y + j P, P = 2 (n - 1).
 * v_out, v_in: [outer, n, inner]; accumulate != 0 adds to v_in instead of overwriting it. */
__kernel void v_conv_axis(__global const float *v_out, __global float *v_in,
                          __global const float *f, const int flen,
                          const int outer, const int n, const int inner, const int accumulate) {
    const int xi = get_global_id(0);            /* y * inner + k */
    const int o = get_global_id(1);
    if (xi >= n * inner || o >= outer) return;
    const int k = xi % inner;
    const int y = xi / inner;
    const size_t gid = (size_t)o * n * inner + xi;
    const int R = flen / 2;
    __global const float *line = v_out + (size_t)o * n * inner + k;
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
    if (accumulate) acc += v_in[gid];
    v_in[gid] = acc;
}

/* Rational resampling by a = p / q (linear interpolation at n_out * p / q):
 * out[o, j, k] = ((q - r) in[o, i0, k] + r in[o, i0 + 1, k]) / q,  j p = i0 q + r, 0 <= r < q.
 * in: [outer, n_in, inner]; out: [outer, n_out, inner], n_out = (n_in - 1) q / p + 1. */
__kernel void resample_axis(__global const float *in, __global float *out,
                            const int p, const int q,
                            const int outer, const int n_in, const int n_out, const int inner) {
    const int xi = get_global_id(0);            /* j * inner + k */
    const int o = get_global_id(1);
    if (xi >= n_out * inner || o >= outer) return;
    const int k = xi % inner;
    const int j = xi / inner;
    const size_t gid = (size_t)o * n_out * inner + xi;
    const int i0 = (j * p) / q;
    const int r = (j * p) - i0 * q;
    __global const float *line = in + (size_t)o * n_in * inner + k;
    float v = line[(size_t)i0 * inner];
    if (r > 0) {  /* then i0 + 1 <= n_in - 1 because j p / q <= n_in - 1 */
        const float w = (float)r / (float)q;
        v = (1.0f - w) * v + w * line[(size_t)(i0 + 1) * inner];
    }
    out[gid] = v;
}

/* Adjoint of resample_axis: v_in[o, i, k] (+)= sum_j max(0, 1 - |j p - i q| / q) v_out[o, j, k],
 * over the j with |j p - i q| < q, i.e. ceil(((i - 1) q + 1) / p) <= j <= floor(((i + 1) q - 1) / p). */
__kernel void v_resample_axis(__global const float *v_out, __global float *v_in,
                              const int p, const int q,
                              const int outer, const int n_in, const int n_out, const int inner,
                              const int accumulate) {
    const int xi = get_global_id(0);            /* i * inner + k */
    const int o = get_global_id(1);
    if (xi >= n_in * inner || o >= outer) return;
    const int k = xi % inner;
    const int i = xi / inner;
    const size_t gid = (size_t)o * n_in * inner + xi;
    const int num_lo = (i - 1) * q + 1;
    int jlo = num_lo > 0 ? (num_lo + p - 1) / p : 0;
    int jhi = ((i + 1) * q - 1) / p;
    if (jhi > n_out - 1) jhi = n_out - 1;
    __global const float *line = v_out + (size_t)o * n_out * inner + k;
    float acc = 0.0f;
    for (int j = jlo; j <= jhi; ++j) {
        const int d = abs(j * p - i * q);
        if (d < q) acc += ((float)(q - d) / (float)q) * line[(size_t)j * inner];
    }
    if (accumulate) acc += v_in[gid];
    v_in[gid] = acc;
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

/* partial[slot * groups + group] = sum of x[i]^2 over this group's grid-stride share of [0, n).
 * Local size must be a power of two; scratch holds one float per work-item. */
__kernel void sumsq_partial(__global const float *x, const int n,
                            __global float *partial, const int slot,
                            __local float *scratch) {
    const int lid = get_local_id(0);
    const int lsize = get_local_size(0);
    const int groups = get_num_groups(0);
    const int stride = get_global_size(0);
    float acc = 0.0f;
    for (int i = get_global_id(0); i < n; i += stride) {
        const float v = x[i];
        acc += v * v;
    }
    scratch[lid] = acc;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int s = lsize / 2; s > 0; s >>= 1) {
        if (lid < s) scratch[lid] += scratch[lid + s];
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    if (lid == 0) partial[slot * groups + get_group_id(0)] = scratch[0];
}
