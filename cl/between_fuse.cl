/* The in-between target's fusion of K flow hypotheses (endowave_cl/ops/between.py between_fuse;
 * reference: endowave_cl/reference/between.py between_fuse_ref, the host path
 * train/between.py fused_interpolation).
 *
 * Per hypothesis k: blend [K, H, W, 3] (its image of the frame at s), diff [K, H, W] (how much its
 * two warps disagree, sum over the channels) and ok [K, H, W] (1 where it may be used).  With AGREE
 * its error is the box mean of diff over (2 FUSE_RADIUS + 1)^2 pixels (border reflected without
 * repeating the edge, as OpenCV's blur; rows, then columns), else 0; a hypothesis that is not ok gets an infinite error
 * unless none is ok at the pixel.  Weights exp((min_k E - E_k) / FUSE_TAU), normalised; out:
 * image [H, W, 3] = sum_k w_k blend_k, weight [H, W] = 1 where some hypothesis is ok, else 0.
 * FUSE_RADIUS, FUSE_TAU_INV (1 / FUSE_TAU) and MAX_K come as build options.  No adjoint. */
#pragma OPENCL FP_CONTRACT OFF

inline int reflect101(int v, const int n) {
    if (n == 1) return 0;
    while (v < 0 || v >= n) v = v < 0 ? -v : 2 * n - 2 - v;
    return v;
}

/* rows [K, H, W]: diff summed over the 2 FUSE_RADIUS + 1 pixels of its row around each pixel
 * (the box mean's first, separable pass) */
__kernel void between_box_rows(__global const float *diff, const int K, const int W, const int H,
                               __global float *rows) {
    const int i = get_global_id(0);
    if (i >= K * W * H) return;
    const int x = i % W, row = i - x;
    float sum = 0.0f;
    for (int dx = -FUSE_RADIUS; dx <= FUSE_RADIUS; ++dx) sum += diff[row + reflect101(x + dx, W)];
    rows[i] = sum;
}

/* rows: between_box_rows of the hypotheses' diff (read with AGREE only) */
__kernel void between_fuse(__global const float *blend, __global const float *rows, __global const float *ok,
                           const int K, const int W, const int H,
                           __global float *image, __global float *weight) {
    const int i = get_global_id(0);
    if (i >= W * H) return;
    const int x = i % W, y = i / W, n = W * H;
    int any_ok = 0;
    for (int k = 0; k < K; ++k) any_ok |= ok[k * n + i] > 0.0f;
    float err[MAX_K];
    float lo = INFINITY;
    for (int k = 0; k < K; ++k) {
        float e = 0.0f;
#ifdef AGREE
        __global const float *r = rows + k * n + x;
        for (int dy = -FUSE_RADIUS; dy <= FUSE_RADIUS; ++dy) e += r[reflect101(y + dy, H) * W];
        e *= 1.0f / (float)((2 * FUSE_RADIUS + 1) * (2 * FUSE_RADIUS + 1));
#endif
        if (any_ok && !(ok[k * n + i] > 0.0f)) e = INFINITY;
        err[k] = e;
        lo = fmin(lo, e);
    }
    float total = 0.0f;
    for (int k = 0; k < K; ++k) {
        err[k] = exp((lo - err[k]) * FUSE_TAU_INV);
        total += err[k];
    }
    float3 out = (float3)(0.0f);
    for (int k = 0; k < K; ++k) out += vload3(k * n + i, blend) * (err[k] / total);
    vstore3(out, i, image);
    weight[i] = any_ok ? 1.0f : 0.0f;
}
