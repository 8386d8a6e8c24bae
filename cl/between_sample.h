/* Sampling as OpenCV's remap does it, for the in-between target's kernels (between_warp.cl,
 * between_push.cl), of a frame stored as [H, W, 4] (RGB and its tool mask, aligned loads): border
 * replicated, the colour bicubic (a = -0.75, OpenCV's coefficients in float; the target always
 * samples so, train/between.py SAMPLER) and the mask bilinear, at the float position (OpenCV 5's
 * remap does not round it); and the paths g = ca A + cb B the kernels read displacements from. */
#ifndef BETWEEN_SAMPLE_H
#define BETWEEN_SAMPLE_H

#define CUBIC_A (-0.75f)
/* inlined into the kernels, so that a CPU driver can vectorise their work-item loops */
#define INLINE inline __attribute__((always_inline))

INLINE int clampi(int v, int hi) { return min(max(v, 0), hi); }

/* OpenCV's interpolateCubic at fraction x, in float */
INLINE float4 cubic_coeffs(const float x) {
    const float c0 = ((CUBIC_A * (x + 1.0f) - 5.0f * CUBIC_A) * (x + 1.0f) + 8.0f * CUBIC_A) * (x + 1.0f) - 4.0f * CUBIC_A;
    const float c1 = ((CUBIC_A + 2.0f) * x - (CUBIC_A + 3.0f)) * x * x + 1.0f;
    const float c2 = ((CUBIC_A + 2.0f) * (1.0f - x) - (CUBIC_A + 3.0f)) * (1.0f - x) * (1.0f - x) + 1.0f;
    return (float4)(c0, c1, c2, 1.0f - c0 - c1 - c2);
}

/* (the pixel index at or left of m, bounded to [-4, n + 3] (the border is replicated from there
 * on), the fraction m - floor(m)); a non-finite m: the first index (NaN, -inf) or the last
 * (+inf) with fraction 0, as remap's bicubic sampling takes it */
INLINE float2 cell(const float m, const int n) {
    const float fl = floor(m);
    return isfinite(m) ? (float2)(clamp(fl, -4.0f, (float)(n + 3)), m - fl)
                       : (float2)(m > 0.0f ? (float)(n - 1) : 0.0f, 0.0f);
}

/* img [H, W, 4] (RGB and the tool mask) at (mx, my), border replicated: .xyz the colour, bicubic;
 * .w the mask, bilinear (its taps are the bicubic's inner four).  A non-finite position gives NaN
 * where remap's bilinear sampling does (the mask). */
INLINE float4 sample_rgbm(__global const float4 *img, const int W, const int H, const float mx, const float my) {
    const float2 cx_ = cell(mx, W), cy_ = cell(my, H);
    const int x0 = (int)cx_.x, y0 = (int)cy_.x;
    const float fx = cx_.y, fy = cy_.y;
    const int xb = clampi(x0, W - 1), xc = clampi(x0 + 1, W - 1);
    __global const float4 *r1 = img + W * clampi(y0, H - 1), *r2 = img + W * clampi(y0 + 1, H - 1);
    const float4 p11 = r1[xb], p12 = r1[xc], p21 = r2[xb], p22 = r2[xc];
    const float4 lin = (p11 * ((1.0f - fy) * (1.0f - fx)) + p12 * ((1.0f - fy) * fx))
                     + (p21 * (fy * (1.0f - fx)) + p22 * (fy * fx));
    const int finite = isfinite(mx) && isfinite(my);
    const float4 cx = cubic_coeffs(fx), cy = cubic_coeffs(fy);
    const int xa = clampi(x0 - 1, W - 1), xd = clampi(x0 + 2, W - 1);
    __global const float4 *r0 = img + W * clampi(y0 - 1, H - 1), *r3 = img + W * clampi(y0 + 2, H - 1);
    float4 sum = (r0[xa] * (cy.x * cx.x) + r0[xb] * (cy.x * cx.y)) + (r0[xc] * (cy.x * cx.z) + r0[xd] * (cy.x * cx.w));
    sum += (r1[xa] * (cy.y * cx.x) + p11 * (cy.y * cx.y)) + (p12 * (cy.y * cx.z) + r1[xd] * (cy.y * cx.w));
    sum += (r2[xa] * (cy.z * cx.x) + p21 * (cy.z * cx.y)) + (p22 * (cy.z * cx.z) + r2[xd] * (cy.z * cx.w));
    sum += (r3[xa] * (cy.w * cx.x) + r3[xb] * (cy.w * cx.y)) + (r3[xc] * (cy.w * cx.z) + r3[xd] * (cy.w * cx.w));
    return (float4)(sum.xyz, finite ? lin.w : NAN);
}

/* the path g = ca A (+ cb B) at pixel i */
INLINE float2 path_at(__global const float *a, const int pa, const int oa, const float ca,
                      __global const float *b, const int pb, const int ob, const float cb, const int nb,
                      const int i) {
    float2 g = (float2)(ca * a[i * pa + oa], ca * a[i * pa + oa + 1]);
    if (nb) g = (float2)(g.x + cb * b[i * pb + ob], g.y + cb * b[i * pb + ob + 1]);
    return g;
}


#endif
