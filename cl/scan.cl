/* Exclusive prefix sum of int32 (docs/ARCHITECTURE.md "bin, sort, ranges").
 *
 * Two kernels, used recursively by endowave_cl/ops/scan.py:
 *   scan_blocks       each work-group scans one block of SCAN_BLOCK values and writes the
 *                     block's total to block_sums[group];
 *   scan_add_offsets  adds the (scanned) block offsets to every value of each block.
 *
 * Build options (defaults below): SCAN_WG work-items per group (a power of two),
 * SCAN_ITEMS consecutive values per work-item.  Sums wrap at 2^31 (callers keep totals
 * below that). */
#include "common.h"

#ifndef SCAN_WG
#define SCAN_WG 256
#endif
#ifndef SCAN_ITEMS
#define SCAN_ITEMS 8
#endif
/* Values scanned by one work-group. */
#define SCAN_BLOCK (SCAN_WG * SCAN_ITEMS)

/* out[k] = sum_{j < k, j in this block} x[j] for k < n_out, reading x[j] = 0 for j >= n_in
 * (so n_out = n_in + 1 also yields the grand total in out[n_in]).
 * block_sums[group] = the block's total.  Global size = num_groups * SCAN_WG. */
__kernel __attribute__((reqd_work_group_size(SCAN_WG, 1, 1)))
void scan_blocks(__global const int *x,      /* [n_in] */
                 const int n_in,
                 __global int *out,          /* [n_out] */
                 const int n_out,
                 __global int *block_sums) { /* [num_groups] */
    __local int sums[SCAN_WG];
    const int l = get_local_id(0);
    const int g = get_group_id(0);
    const int base = g * SCAN_BLOCK + l * SCAN_ITEMS;

    int v[SCAN_ITEMS];
    int s = 0;
    for (int j = 0; j < SCAN_ITEMS; ++j) {
        const int idx = base + j;
        v[j] = (idx < n_in) ? x[idx] : 0;
        s += v[j];
    }
    sums[l] = s;
    barrier(CLK_LOCAL_MEM_FENCE);
    /* Hillis-Steele inclusive scan of the per-item sums; read, barrier, write, barrier. */
    for (int off = 1; off < SCAN_WG; off <<= 1) {
        const int t = (l >= off) ? sums[l - off] : 0;
        barrier(CLK_LOCAL_MEM_FENCE);
        sums[l] += t;
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    int run = sums[l] - s; /* exclusive prefix of this item within the block */
    for (int j = 0; j < SCAN_ITEMS; ++j) {
        const int idx = base + j;
        if (idx < n_out) out[idx] = run;
        run += v[j];
    }
    if (l == SCAN_WG - 1) block_sums[g] = sums[l];
}

/* out[k] += block_offsets[k / SCAN_BLOCK] for k < n_out. */
__kernel void scan_add_offsets(__global int *out,                 /* [n_out] */
                               const int n_out,
                               __global const int *block_offsets) { /* [num_groups] */
    const int k = get_global_id(0);
    if (k >= n_out) return;
    out[k] += block_offsets[k / SCAN_BLOCK];
}
