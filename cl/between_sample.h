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
/* OpenCV's Lanczos-4 weights (imgproc's interpolateLanczos4) at fraction k / 32, k = 0 .. 31, of
 * the taps at x0 - 3 .. x0 + 4: sin(pi t) sin(pi t / 4) / t^2 for the distance t from the position
 * to the tap, computed in double, normalised to sum 1 and rounded to float (fraction 0 takes the
 * pixel itself); a table, since sin and cos per sample doubled the sampler's time on a CPU.  The
 * kernels' tests compare the sampling with cv2.remap's. */
__constant float LANCZOS4_TAB[32][8] = {
    {0.0f, 0.0f, 0.0f, 1.0f,
     0.0f, 0.0f, 0.0f, 0.0f},
    {-2.9810278e-3f, 9.62481e-3f, -2.7052572e-2f, 9.982653e-1f,
     2.9186774e-2f, -1.0245609e-2f, 3.2642935e-3f, -6.189258e-5f},
    {-5.6608217e-3f, 1.8562486e-2f, -5.188946e-2f, 9.930771e-1f,
     6.040726e-2f, -2.103491e-2f, 6.7886175e-3f, -2.502084e-4f},
    {-8.02671e-3f, 2.675789e-2f, -7.444909e-2f, 9.844779e-1f,
     9.354314e-2f, -3.2280616e-2f, 1.0544587e-2f, -5.6705927e-4f},
    {-1.0071198e-2f, 3.4167126e-2f, -9.468974e-2f, 9.725335e-1f,
     1.2845916e-1f, -4.3885775e-2f, 1.4498807e-2f, -1.0120017e-3f},
    {-1.1791785e-2f, 4.0757455e-2f, -1.1258936e-1f, 9.5733285e-1f,
     1.6500413e-1f, -5.57444e-2f, 1.861307e-2f, -1.58195e-3f},
    {-1.3190699e-2f, 4.6507046e-2f, -1.28145e-1f, 9.3898547e-1f,
     2.0301189e-1f, -6.774213e-2f, 2.2844613e-2f, -2.2711284e-3f},
    {-1.4274589e-2f, 5.1404618e-2f, -1.4137214e-1f, 9.176212e-1f,
     2.4230257e-1f, -7.9757065e-2f, 2.714645e-2f, -3.0710634e-3f},
    {-1.5054175e-2f, 5.5448987e-2f, -1.523039e-1f, 8.9338857e-1f,
     2.8268394e-1f, -9.1660574e-2f, 3.146775e-2f, -3.970616e-3f},
    {-1.5543843e-2f, 5.8648467e-2f, -1.6098998e-1f, 8.6645293e-1f,
     3.2395247e-1f, -1.03318244e-1f, 3.5754282e-2f, -4.956054e-3f},
    {-1.5761226e-2f, 6.102027e-2f, -1.674955e-1f, 8.3699465e-1f,
     3.658949e-1f, -1.14590876e-1f, 3.99489e-2f, -6.011165e-3f},
    {-1.5726764e-2f, 6.2589765e-2f, -1.7189984e-1f, 8.052081e-1f,
     4.082896e-1f, -1.253355e-1f, 4.399208e-2f, -7.1174065e-3f},
    {-1.5463231e-2f, 6.3389726e-2f, -1.7429528e-1f, 7.71299e-1f,
     4.509078e-1f, -1.3540645e-1f, 4.7822513e-2f, -8.254092e-3f},
    {-1.4995287e-2f, 6.3459545e-2f, -1.7478575e-1f, 7.354837e-1f,
     4.9351525e-1f, -1.4465652e-1f, 5.137773e-2f, -9.39862e-3f},
    {-1.4349009e-2f, 6.28444e-2f, -1.7348535e-1f, 6.9798654e-1f,
     5.358735e-1f, -1.5293816e-1f, 5.4594737e-2f, -1.0526729e-2f},
    {-1.3551444e-2f, 6.1594497e-2f, -1.705171e-1f, 6.59039e-1f,
     5.777416e-1f, -1.6010465e-1f, 5.74108e-2f, -1.1612795e-2f},
    {-1.2630151e-2f, 5.9764087e-2f, -1.6601135e-1f, 6.188774e-1f,
     6.188774e-1f, -1.6601135e-1f, 5.9764087e-2f, -1.2630151e-2f},
    {-1.1612795e-2f, 5.74108e-2f, -1.6010465e-1f, 5.777416e-1f,
     6.59039e-1f, -1.705171e-1f, 6.1594497e-2f, -1.3551444e-2f},
    {-1.0526729e-2f, 5.4594737e-2f, -1.5293816e-1f, 5.358735e-1f,
     6.9798654e-1f, -1.7348535e-1f, 6.28444e-2f, -1.4349009e-2f},
    {-9.39862e-3f, 5.137773e-2f, -1.4465652e-1f, 4.9351525e-1f,
     7.354837e-1f, -1.7478575e-1f, 6.3459545e-2f, -1.4995287e-2f},
    {-8.254092e-3f, 4.7822513e-2f, -1.3540645e-1f, 4.509078e-1f,
     7.71299e-1f, -1.7429528e-1f, 6.3389726e-2f, -1.5463231e-2f},
    {-7.1174065e-3f, 4.399208e-2f, -1.253355e-1f, 4.082896e-1f,
     8.052081e-1f, -1.7189984e-1f, 6.2589765e-2f, -1.5726764e-2f},
    {-6.011165e-3f, 3.99489e-2f, -1.14590876e-1f, 3.658949e-1f,
     8.3699465e-1f, -1.674955e-1f, 6.102027e-2f, -1.5761226e-2f},
    {-4.956054e-3f, 3.5754282e-2f, -1.03318244e-1f, 3.2395247e-1f,
     8.6645293e-1f, -1.6098998e-1f, 5.8648467e-2f, -1.5543843e-2f},
    {-3.970616e-3f, 3.146775e-2f, -9.1660574e-2f, 2.8268394e-1f,
     8.9338857e-1f, -1.523039e-1f, 5.5448987e-2f, -1.5054175e-2f},
    {-3.0710634e-3f, 2.714645e-2f, -7.9757065e-2f, 2.4230257e-1f,
     9.176212e-1f, -1.4137214e-1f, 5.1404618e-2f, -1.4274589e-2f},
    {-2.2711284e-3f, 2.2844613e-2f, -6.774213e-2f, 2.0301189e-1f,
     9.3898547e-1f, -1.28145e-1f, 4.6507046e-2f, -1.3190699e-2f},
    {-1.58195e-3f, 1.861307e-2f, -5.57444e-2f, 1.6500413e-1f,
     9.5733285e-1f, -1.1258936e-1f, 4.0757455e-2f, -1.1791785e-2f},
    {-1.0120017e-3f, 1.4498807e-2f, -4.3885775e-2f, 1.2845916e-1f,
     9.725335e-1f, -9.468974e-2f, 3.4167126e-2f, -1.0071198e-2f},
    {-5.6705927e-4f, 1.0544587e-2f, -3.2280616e-2f, 9.354314e-2f,
     9.844779e-1f, -7.444909e-2f, 2.675789e-2f, -8.02671e-3f},
    {-2.502084e-4f, 6.7886175e-3f, -2.103491e-2f, 6.040726e-2f,
     9.930771e-1f, -5.188946e-2f, 1.8562486e-2f, -5.6608217e-3f},
    {-6.189258e-5f, 3.2642935e-3f, -1.0245609e-2f, 2.9186774e-2f,
     9.982653e-1f, -2.7052572e-2f, 9.62481e-3f, -2.9810278e-3f}
};

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
    __constant const float *cx = LANCZOS4_TAB[cx_.y], *cy = LANCZOS4_TAB[cy_.y];
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
