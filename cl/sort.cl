/* Stable LSD radix sort of (ulong key, int value) pairs: one pass per RADIX_BITS-bit digit
 * (docs/ARCHITECTURE.md "bin, sort, ranges"; host side endowave_cl/ops/sort.py).
 *
 * The keys are cut into blocks of SORT_WG * items keys, one block per work-group; each
 * work-item owns `items` consecutive keys (its chunk) and walks them in order, which is what
 * makes the pass stable.  A pass is:
 *   radix_histogram  per block and digit, how many keys have that digit -> hist [RADIX, n_blocks]
 *   (host)           exclusive scan of hist, flattened digit-major: the output position of the
 *                    first key of digit d in block b (cl/scan.cl)
 *   radix_scatter    each work-item counts its chunk again, the work-group turns the counts into
 *                    per-(digit, work-item) output positions in chunk order, then each work-item
 *                    writes its keys and values there in order.
 *
 * Build options: RADIX_BITS (digit width, 1..12), SORT_WG (work-items per group; with 1, the
 * scatter reuses the histogram's counts instead of counting again: the fast choice on CPUs).
 * Local memory: RADIX * SORT_WG ints. */
#include "common.h"

#ifndef RADIX_BITS
#define RADIX_BITS 8
#endif
#ifndef SORT_WG
#define SORT_WG 16
#endif
/* Number of distinct digit values. */
#define RADIX (1 << RADIX_BITS)
#define DIGIT_MASK (RADIX - 1)

inline int digit_of(const ulong key, const int shift) {
    return (int)((key >> shift) & (ulong)DIGIT_MASK);
}

/* counts[d * SORT_WG + l] = number of keys with digit d in work-item l's chunk [start, end).
 * Each work-item touches only its own column l. */
inline void count_chunk(__global const ulong *keys, const int start, const int end,
                        const int shift, __local int *counts, const int l) {
    for (int d = 0; d < RADIX; ++d) counts[d * SORT_WG + l] = 0;
    for (int i = start; i < end; ++i) counts[digit_of(keys[i], shift) * SORT_WG + l] += 1;
}

/* hist[d * n_blocks + b] = number of keys of digit d in block b.
 * Global size n_blocks * SORT_WG; n_blocks * SORT_WG * items >= n. */
__kernel __attribute__((reqd_work_group_size(SORT_WG, 1, 1)))
void radix_histogram(__global const ulong *keys, /* [n] */
                     const int n,
                     const int items,
                     const int shift,
                     const int n_blocks,
                     __global int *hist) {        /* [RADIX, n_blocks] */
    __local int counts[RADIX * SORT_WG];          /* [RADIX, SORT_WG] */
    const int l = get_local_id(0);
    const int b = get_group_id(0);
    const int start = min(n, (b * SORT_WG + l) * items);
    const int end = min(n, start + items);
    count_chunk(keys, start, end, shift, counts, l);
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int d = l; d < RADIX; d += SORT_WG) {
        int s = 0;
        for (int w = 0; w < SORT_WG; ++w) s += counts[d * SORT_WG + w];
        hist[d * n_blocks + b] = s;
    }
}

/* Stable scatter of one pass.  offsets = exclusive scan of hist (same layout). */
__kernel __attribute__((reqd_work_group_size(SORT_WG, 1, 1)))
void radix_scatter(__global const ulong *keys_in,  /* [n] */
                   __global const int *vals_in,    /* [n] */
                   const int n,
                   const int items,
                   const int shift,
                   const int n_blocks,
                   __global const int *offsets,    /* [RADIX, n_blocks] */
                   __global ulong *keys_out,       /* [n] */
                   __global int *vals_out) {       /* [n] */
    __local int pos[RADIX * SORT_WG];              /* [RADIX, SORT_WG] */
    const int l = get_local_id(0);
    const int b = get_group_id(0);
    const int start = min(n, (b * SORT_WG + l) * items);
    const int end = min(n, start + items);
#if SORT_WG == 1
    /* One work-item per block: the block's offsets are its own output positions already,
     * so the keys need not be counted again. */
    for (int d = 0; d < RADIX; ++d) pos[d] = offsets[d * n_blocks + b];
#else
    count_chunk(keys_in, start, end, shift, pos, l);
    barrier(CLK_LOCAL_MEM_FENCE);
    /* Counts -> first output position of each (digit, work-item), work-items in chunk order. */
    for (int d = l; d < RADIX; d += SORT_WG) {
        int run = offsets[d * n_blocks + b];
        for (int w = 0; w < SORT_WG; ++w) {
            const int c = pos[d * SORT_WG + w];
            pos[d * SORT_WG + w] = run;
            run += c;
        }
    }
    barrier(CLK_LOCAL_MEM_FENCE);
#endif
    for (int i = start; i < end; ++i) {
        const ulong key = keys_in[i];
        const int slot = digit_of(key, shift) * SORT_WG + l;
        const int p = pos[slot];
        pos[slot] = p + 1;
        keys_out[p] = key;
        vals_out[p] = vals_in[i];
    }
}
