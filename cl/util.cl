/* Small utility kernels shared by the host code. */
#include "common.h"

/* x[i] = value for i < n. */
__kernel void fill_f32(__global float *x, const float value, const int n) {
    int i = get_global_id(0);
    if (i < n) x[i] = value;
}

/* out[i] += x[i] for i < n. */
__kernel void add_inplace_f32(__global float *out, __global const float *x, const int n) {
    int i = get_global_id(0);
    if (i < n) out[i] += x[i];
}

/* Sum of x[i] into *out with the CAS float add: a test of atomic_add_global_f.
 * Each work-group reduces in local memory, then adds once. */
__kernel void atomic_sum_f32(__global const float *x, const int n, volatile __global float *out,
                             __local float *scratch) {
    int i = get_global_id(0);
    int l = get_local_id(0);
    scratch[l] = (i < n) ? x[i] : 0.0f;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int s = get_local_size(0) / 2; s > 0; s >>= 1) {
        if (l < s) scratch[l] += scratch[l + s];
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    if (l == 0) atomic_add_global_f(out, scratch[0]);
}

/* flag[0] |= 1 if any of x[0..n) is NaN or +-Inf (the training step's divergence guard). */
__kernel void any_nonfinite_f32(__global const float *x, const int n, volatile __global int *flag) {
    int i = get_global_id(0);
    if (i < n && !isfinite(x[i])) atomic_or(flag, 1);
}
