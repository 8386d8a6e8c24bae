/* Sampling as OpenCV's remap does it, for the in-between target's kernels (between_warp.cl,
 * between_push.cl), of a frame stored as [H, W, 4] (RGB and its tool mask, aligned loads): border
 * replicated, the mask bilinear at the float position (OpenCV 5's remap does not round it), the
 * colour by the sampler train/between.py SAMPLER names: bicubic (a = -0.75, OpenCV's coefficients in
 * float, at the float position) or, built with -DLANCZOS4, Lanczos-4 (8 x 8 taps, the position
 * rounded to 1/32 pixel as remap rounds it for that sampler); and the paths g = ca A + cb B the
 * kernels read displacements from. */
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

#ifdef LANCZOS4
/* OpenCV's interpolateLanczos4 at fraction k / 32: the weights of the taps at x0 - 3 .. x0 + 4,
 * sin(pi t) sin(pi t / 4) / t^2 for the distance t from the position to the tap, normalised to sum
 * 1 (the factor sin(pi k / 32) that every tap shares is left out); fraction 0 takes the pixel */
INLINE void lanczos4_coeffs(const int k, float c[8]) {
    if (k == 0) {
        for (int i = 0; i < 8; ++i) c[i] = i == 3 ? 1.0f : 0.0f;
        return;
    }
    const float s45 = 0.70710678118654752f;
    const float cs[8][2] = {{1.0f, 0.0f}, {-s45, -s45}, {0.0f, 1.0f}, {s45, -s45},
                            {-1.0f, 0.0f}, {s45, s45}, {0.0f, -1.0f}, {-s45, s45}};
    const float x = (float)k * (1.0f / 32.0f);
    const float y0 = -(x + 3.0f) * (M_PI_F * 0.25f);
    const float s0 = sin(y0), c0 = cos(y0);
    float sum = 0.0f;
    for (int i = 0; i < 8; ++i) {
        const float y = -(x + (float)(3 - i)) * (M_PI_F * 0.25f);
        c[i] = (cs[i][0] * s0 + cs[i][1] * c0) / (y * y);
        sum += c[i];
    }
    const float inv = 1.0f / sum;
    for (int i = 0; i < 8; ++i) c[i] *= inv;
}

/* remap's Lanczos-4 cell of position m on an axis of n pixels: (the tap block's centre pixel x0,
 * the fraction in 1/32 pixels), m * 32 rounded half to even; NaN and +inf take the last pixel,
 * -inf the first, and positions far past the border are bounded (every tap is then the border
 * pixel, as the replicated border gives) */
INLINE int2 lanczos_cell(const float m, const int n) {
    const float b = isnan(m) ? (float)(n + 8) : clamp(m, -8.0f, (float)(n + 8));
    const int q = (int)rint(b * 32.0f);
    return (int2)(q >> 5, q & 31);
}

/* img's colour [H, W, 4] (.xyz) at (mx, my) by Lanczos-4, border replicated */
INLINE float3 sample_rgb_lanczos4(__global const float4 *img, const int W, const int H, const float mx, const float my) {
    const int2 cx_ = lanczos_cell(mx, W), cy_ = lanczos_cell(my, H);
    float cx[8], cy[8];
    lanczos4_coeffs(cx_.y, cx);
    lanczos4_coeffs(cy_.y, cy);
    int xs[8];
    for (int i = 0; i < 8; ++i) xs[i] = clampi(cx_.x - 3 + i, W - 1);
    float3 sum = (float3)(0.0f);
    for (int j = 0; j < 8; ++j) {
        __global const float4 *row = img + W * clampi(cy_.x - 3 + j, H - 1);
        float3 r = (float3)(0.0f);
        for (int i = 0; i < 8; ++i) r += row[xs[i]].xyz * cx[i];
        sum += r * cy[j];
    }
    return sum;
}
#endif

/* img [H, W, 4] (RGB and the tool mask) at (mx, my), border replicated: .xyz the colour, bicubic
 * (or Lanczos-4, -DLANCZOS4); .w the mask, bilinear (its taps are the bicubic's inner four).  A
 * non-finite position gives NaN where remap's bilinear sampling does (the mask). */
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
#ifdef LANCZOS4
    const float3 colour = sample_rgb_lanczos4(img, W, H, mx, my);
#else
    const float4 cx = cubic_coeffs(fx), cy = cubic_coeffs(fy);
    const int xa = clampi(x0 - 1, W - 1), xd = clampi(x0 + 2, W - 1);
    __global const float4 *r0 = img + W * clampi(y0 - 1, H - 1), *r3 = img + W * clampi(y0 + 2, H - 1);
    float4 sum = (r0[xa] * (cy.x * cx.x) + r0[xb] * (cy.x * cx.y)) + (r0[xc] * (cy.x * cx.z) + r0[xd] * (cy.x * cx.w));
    sum += (r1[xa] * (cy.y * cx.x) + p11 * (cy.y * cx.y)) + (p12 * (cy.y * cx.z) + r1[xd] * (cy.y * cx.w));
    sum += (r2[xa] * (cy.z * cx.x) + p21 * (cy.z * cx.y)) + (p22 * (cy.z * cx.z) + r2[xd] * (cy.z * cx.w));
    sum += (r3[xa] * (cy.w * cx.x) + r3[xb] * (cy.w * cx.y)) + (r3[xc] * (cy.w * cx.z) + r3[xd] * (cy.w * cx.w));
    const float3 colour = sum.xyz;
#endif
    return (float4)(colour, finite ? lin.w : NAN);
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
