/* Densification statistics (docs/ARCHITECTURE.md "rasterize", 3DGS's densify bookkeeping).
 * OpenCL C 1.2.  One work-item per Gaussian; in place.
 *
 * For a visible Gaussian (radius > 0):
 *   grad_accum += |v_means2d * (W/2, H/2)|   (norm of the screen-space mean gradient in NDC units)
 *   count      += 1
 *   max_radius  = max(max_radius, radius)
 * accumulate_densify_stats_rows: the same for a step on selected rows (ops/select.py): entry i of
 * v_means2d / radius belongs to Gaussian rows[i] of the statistics.
 */
inline void densify_stats_entry(const float2 vm, const int r, const float half_w, const float half_h,
                                const int j, __global float *grad_accum, __global int *count,
                                __global float *max_radius) {
    const float2 v = vm * (float2)(half_w, half_h);
    grad_accum[j] += sqrt(v.x * v.x + v.y * v.y);
    count[j] += 1;
    max_radius[j] = fmax(max_radius[j], (float)r);
}

__kernel void accumulate_densify_stats(__global const float2 *v_means2d, /* [N, 2] */
                                       __global const int *radius,       /* [N] */
                                       const float half_w, const float half_h, const int n,
                                       __global float *grad_accum,       /* [N] */
                                       __global int *count,              /* [N] */
                                       __global float *max_radius)       /* [N] */
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const int r = radius[i];
    if (r <= 0) return;
    densify_stats_entry(v_means2d[i], r, half_w, half_h, i, grad_accum, count, max_radius);
}

__kernel void accumulate_densify_stats_rows(__global const float2 *v_means2d, /* [L, 2] */
                                            __global const int *radius,       /* [L] */
                                            const float half_w, const float half_h, const int n,
                                            __global const int *rows,         /* [L] */
                                            __global float *grad_accum,       /* [N] */
                                            __global int *count,              /* [N] */
                                            __global float *max_radius)       /* [N] */
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const int r = radius[i];
    if (r <= 0) return;
    densify_stats_entry(v_means2d[i], r, half_w, half_h, rows[i], grad_accum, count, max_radius);
}
