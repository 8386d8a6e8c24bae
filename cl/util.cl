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

/* avg[i] += w (x[i] - avg[i]) for i < n: with w = 1 / k at the k-th snapshot, avg is the uniform
 * mean of the snapshots so far (train/average.py: the parameters averaged over the last steps). */
__kernel void average_into_f32(__global float *avg, __global const float *x, const float w, const int n) {
    int i = get_global_id(0);
    if (i < n) avg[i] += w * (x[i] - avg[i]);
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

/* flag[0] |= 1 if any element of the arrays x0 .. x7 (n0 .. n7 elements; n = 0 for an unused slot)
 * is NaN or +-Inf (the training step's divergence guard, one launch for all the step's gradients).
 * Work-item (i, a) checks elements [NF_RUN i, NF_RUN (i + 1)) of array a (the last run may be
 * shorter), 8 at a time: a float is NaN or Inf exactly when its exponent bits are all set (a bit
 * test: isfinite is an out-of-line call on PoCL).  One atomic per work-item that found one. */
#ifdef NF_RUN   /* built with -DNF_RUN (ops/util.py NONFINITE_RUN) */
#define EXP_MASK 0x7f800000
__kernel void any_nonfinite_f32(__global const float *x0, const int n0, __global const float *x1, const int n1,
                                __global const float *x2, const int n2, __global const float *x3, const int n3,
                                __global const float *x4, const int n4, __global const float *x5, const int n5,
                                __global const float *x6, const int n6, __global const float *x7, const int n7,
                                volatile __global int *flag) {
    const int a = get_global_id(1);
    __global const float *x = a == 0 ? x0 : a == 1 ? x1 : a == 2 ? x2 : a == 3 ? x3
                            : a == 4 ? x4 : a == 5 ? x5 : a == 6 ? x6 : x7;
    const int n = a == 0 ? n0 : a == 1 ? n1 : a == 2 ? n2 : a == 3 ? n3
                : a == 4 ? n4 : a == 5 ? n5 : a == 6 ? n6 : n7;
    const int j0 = get_global_id(0) * NF_RUN;
    if (j0 >= n) return;
    int bad = 0;
    if (j0 + NF_RUN <= n) {
        int8 hit = (int8)(0);
        for (int k = 0; k < NF_RUN; k += 8)
            hit |= (as_int8(load8(x + j0 + k)) & EXP_MASK) == (int8)(EXP_MASK);
        bad = hit.s0 | hit.s1 | hit.s2 | hit.s3 | hit.s4 | hit.s5 | hit.s6 | hit.s7;
    } else {
        for (int j = j0; j < n; j++) bad |= (as_int(x[j]) & EXP_MASK) == EXP_MASK;
    }
    if (bad) atomic_or(flag, 1);
}
#endif  /* NF_RUN */

/* The training step's gate (ops/util.py step_gate), one work-item: skip[0] |= the reasons the
 * step's update must not be applied, so that Adam and the densification statistics, which read
 * skip[0], leave everything as it was.  Sticky: a later step's gate keeps the bits, so every step
 * enqueued behind a skipped one is skipped too, until the host has read them and cleared skip.
 *   GATE_NONFINITE   the gradients or the loss sums hold a NaN or an Inf (nonfinite_grads[0] or
 *                    nonfinite_loss[0] != 0: ops/util.py nonfinite_flag of each)
 *   GATE_ROWS        the live rows overflowed their buffer: rows_count[rows_at] > rows_cap
 *   GATE_PAIRS       the binning's pairs overflowed theirs: pairs_count[pairs_at] > pairs_cap
 *   GATE_SUPERVISED  the target supervises no pixel (supervised[0] == 0, where check_supervised)
 * A capacity < 0 leaves its test out (a count the host knew when it sized the buffer). */
#ifdef GATE_NONFINITE   /* built with the bits of ops/util.py GATE_BITS */
__kernel void step_gate(__global const int *nonfinite_grads, __global const int *nonfinite_loss,
                        __global const int *rows_count, const int rows_at,
                        const int rows_cap, __global const int *pairs_count, const int pairs_at,
                        const int pairs_cap, __global const int *supervised, const int check_supervised,
                        __global int *skip) {
    if (get_global_id(0) != 0) return;
    int s = skip[0];
    if (nonfinite_grads[0] != 0 || nonfinite_loss[0] != 0) s |= GATE_NONFINITE;
    if (rows_cap >= 0 && rows_count[rows_at] > rows_cap) s |= GATE_ROWS;
    if (pairs_cap >= 0 && pairs_count[pairs_at] > pairs_cap) s |= GATE_PAIRS;
    if (check_supervised && supervised[0] == 0) s |= GATE_SUPERVISED;
    skip[0] = s;
}
#endif  /* GATE_NONFINITE */
