/* Densification statistics (docs/ARCHITECTURE.md "rasterize", 3DGS's densify bookkeeping).
 * OpenCL C 1.2.  One work-item per Gaussian; in place.
 *
 * For a visible Gaussian (radius > 0):
 *   grad_accum += |v_means2d * (W/2, H/2)|   (norm of the screen-space mean gradient in NDC units)
 *   count      += 1
 *   max_radius  = max(max_radius, radius)
 */
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
    const float2 v = v_means2d[i] * (float2)(half_w, half_h);
    grad_accum[i] += sqrt(v.x * v.x + v.y * v.y);
    count[i] += 1;
    max_radius[i] = fmax(max_radius[i], (float)r);
}
