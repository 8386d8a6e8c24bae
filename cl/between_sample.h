/* Sampling as OpenCV's remap does it, for the in-between target's kernels (between_warp.cl,
 * between_push.cl): border replicated, bicubic (CUBIC defined; a = -0.75, OpenCV's coefficients in float) or bilinear, at
 * the float position (OpenCV 5's remap does not round it); and the paths g = ca A + cb B the
 * kernels read displacements from. */
#ifndef BETWEEN_SAMPLE_H
#define BETWEEN_SAMPLE_H

#define CUBIC_A (-0.75f)

inline int clampi(int v, int hi) { return min(max(v, 0), hi); }

/* OpenCV's interpolateCubic at fraction x, in float */
inline void cubic_coeffs(float x, float *c) {
    c[0] = ((CUBIC_A * (x + 1.0f) - 5.0f * CUBIC_A) * (x + 1.0f) + 8.0f * CUBIC_A) * (x + 1.0f) - 4.0f * CUBIC_A;
    c[1] = ((CUBIC_A + 2.0f) * x - (CUBIC_A + 3.0f)) * x * x + 1.0f;
    c[2] = ((CUBIC_A + 2.0f) * (1.0f - x) - (CUBIC_A + 3.0f)) * (1.0f - x) * (1.0f - x) + 1.0f;
    c[3] = 1.0f - c[0] - c[1] - c[2];
}

/* the pixel index at or left of m, bounded to [-4, n + 3] (the border is replicated from there
 * on), and the fraction m - floor(m); a non-finite m: the first index (NaN, -inf) or the last
 * (+inf) with fraction 0, as remap's bicubic sampling takes it */
inline int cell(const float m, const int n, float *f) {
    if (!isfinite(m)) {
        *f = 0.0f;
        return m > 0.0f ? n - 1 : 0;
    }
    const float fl = floor(m);
    *f = m - fl;
    return (int)clamp(fl, -4.0f, (float)(n + 3));
}

/* img [H, W, 3] at (mx, my), border replicated: bicubic with CUBIC, else bilinear (a non-finite
 * position gives NaN there, as remap's bilinear sampling) */
inline float3 sample_rgb(__global const float *img, const int W, const int H, const float mx, const float my) {
    float fx, fy;
    const int x0 = cell(mx, W, &fx), y0 = cell(my, H, &fy);
    float3 sum = (float3)(0.0f);
#ifdef CUBIC
    float cx[4], cy[4];
    cubic_coeffs(fx, cx);
    cubic_coeffs(fy, cy);
    for (int r = 0; r < 4; ++r) {
        const int yy = clampi(y0 - 1 + r, H - 1);
        float3 row = (float3)(0.0f);
        for (int c = 0; c < 4; ++c) row += vload3(yy * W + clampi(x0 - 1 + c, W - 1), img) * (cy[r] * cx[c]);
        sum += row;
    }
#else
    if (!(isfinite(mx) && isfinite(my))) return (float3)(NAN);
    const float cx[2] = {1.0f - fx, fx}, cy[2] = {1.0f - fy, fy};
    for (int r = 0; r < 2; ++r) {
        const int yy = clampi(y0 + r, H - 1);
        for (int c = 0; c < 2; ++c) sum += vload3(yy * W + clampi(x0 + c, W - 1), img) * (cy[r] * cx[c]);
    }
#endif
    return sum;
}

/* mask [H, W] at (mx, my), bilinearly, border replicated (NaN at a non-finite position) */
inline float sample_mask(__global const float *m, const int W, const int H, const float mx, const float my) {
    if (!(isfinite(mx) && isfinite(my))) return NAN;
    float fx, fy;
    const int x0 = cell(mx, W, &fx), y0 = cell(my, H, &fy);
    const int xa = clampi(x0, W - 1), xb = clampi(x0 + 1, W - 1);
    const int ya = clampi(y0, H - 1), yb = clampi(y0 + 1, H - 1);
    return (m[ya * W + xa] * ((1.0f - fy) * (1.0f - fx)) + m[ya * W + xb] * ((1.0f - fy) * fx))
         + (m[yb * W + xa] * (fy * (1.0f - fx)) + m[yb * W + xb] * (fy * fx));
}

/* the path g = ca A (+ cb B) at pixel i */
inline float2 path_at(__global const float *a, const int pa, const int oa, const float ca,
                      __global const float *b, const int pb, const int ob, const float cb, const int nb,
                      const int i) {
    float2 g = (float2)(ca * a[i * pa + oa], ca * a[i * pa + oa + 1]);
    if (nb) g = (float2)(g.x + cb * b[i * pb + ob], g.y + cb * b[i * pb + ob + 1]);
    return g;
}

/* where p + d lies */
inline float2 position(const int x, const int y, const float2 d) { return (float2)((float)x + d.x, (float)y + d.y); }

#endif
