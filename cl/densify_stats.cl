/* Densification statistics (docs/ARCHITECTURE.md "rasterize", 3DGS's densify bookkeeping).
 * OpenCL C 1.2.  One work-item per Gaussian of the step; in place.
 *
 * For a visible Gaussian (radius > 0):
 *   grad_accum += |v_means2d * (W/2, H/2)|   (norm of the screen-space mean gradient in NDC units)
 *   count      += 1
 *   max_radius  = max(max_radius, radius)
 * has_rows: the step ran on selected rows (ops/select.py), and entry i of v_means2d / radius
 * belongs to Gaussian rows[i] of the statistics; else to Gaussian i (rows is not read).
 * gated: nothing is accumulated where skip[0] != 0 (cl/util.cl step_gate).
 */
__kernel void accumulate_densify_stats(__global const float2 *v_means2d, /* [L, 2] */
                                       __global const int *radius,       /* [L] */
                                       const float half_w, const float half_h, const int n,
                                       __global const int *rows,         /* [L] when has_rows */
                                       const int has_rows,
                                       __global float *grad_accum,       /* [N] */
                                       __global int *count,              /* [N] */
                                       __global float *max_radius,       /* [N] */
                                       __global const int *skip,         /* [1] the step gate */
                                       const int gated)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    if (gated && skip[0] != 0) return;   /* a skipped step (cl/util.cl step_gate): nothing changes */
    const int r = radius[i];
    if (r <= 0) return;
    const int j = has_rows ? rows[i] : i;
    if (j < 0) return;   /* padding after the selected rows (ops/select.py) */
    const float2 v = v_means2d[i] * (float2)(half_w, half_h);
    grad_accum[j] += sqrt(v.x * v.x + v.y * v.y);
    count[j] += 1;
    max_radius[j] = fmax(max_radius[j], (float)r);
}
