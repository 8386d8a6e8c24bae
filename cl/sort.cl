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
 * Limits kept on the device (ops/sort.py radix_sort_pairs' count and key_bits), read from one int
 * buffer `limits` where their index is >= 0 (-1: not given; any buffer then):
 *   limits[n_at]     the keys are the first min(n, limits[n_at]) of the n the buffers hold (the
 *                    launch is sized for n; the buffers' tail is neither read nor written);
 *   limits[bits_at]  no key has a set bit at or above it: a pass whose digit lies there would
 *                    leave the keys in order, so it copies them instead (its histogram is zeros).
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

/* The keys sorted: the first n, or min(n, limits[n_at]) where n_at >= 0. */
inline int keys_sorted(const int n, __global const int *limits, const int n_at) {
    return n_at < 0 ? n : clamp(limits[n_at], 0, n);
}

/* Whether the pass at shift can move a key: always, or where bits_at >= 0 only below limits[bits_at]. */
inline bool pass_moves(const int shift, __global const int *limits, const int bits_at) {
    return bits_at < 0 || shift < limits[bits_at];
}

/* counts[d * SORT_WG + l] = number of keys with digit d in work-item l's chunk [start, end).
 * Each work-item touches only its own column l. */
inline void count_chunk(__global const ulong *keys, const int start, const int end,
                        const int shift, __local int *counts, const int l) {
    for (int d = 0; d < RADIX; ++d) counts[d * SORT_WG + l] = 0;
    for (int i = start; i < end; ++i) counts[digit_of(keys[i], shift) * SORT_WG + l] += 1;
}

/* hist[d * n_blocks + b] = number of keys of digit d in block b (zeros for a pass that copies).
 * Global size n_blocks * SORT_WG; n_blocks * SORT_WG * items >= n. */
__kernel __attribute__((reqd_work_group_size(SORT_WG, 1, 1)))
void radix_histogram(__global const ulong *keys,   /* [n] */
                     const int n_keys,
                     const int items,
                     const int shift,
                     const int n_blocks,
                     __global int *hist,            /* [RADIX, n_blocks] */
                     __global const int *limits,    /* see the top of the file */
                     const int n_at,
                     const int bits_at) {
    __local int counts[RADIX * SORT_WG];            /* [RADIX, SORT_WG] */
    const int l = get_local_id(0);
    const int b = get_group_id(0);
    if (!pass_moves(shift, limits, bits_at)) {
        for (int d = l; d < RADIX; d += SORT_WG) hist[d * n_blocks + b] = 0;
        return;
    }
    const int n = keys_sorted(n_keys, limits, n_at);
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

/* Stable scatter of one pass.  offsets = exclusive scan of hist (same layout).  A pass that
 * cannot move a key (limits[bits_at]) copies each work-item's chunk in place instead. */
__kernel __attribute__((reqd_work_group_size(SORT_WG, 1, 1)))
void radix_scatter(__global const ulong *keys_in,  /* [n] */
                   __global const int *vals_in,    /* [n] */
                   const int n_keys,
                   const int items,
                   const int shift,
                   const int n_blocks,
                   __global const int *offsets,    /* [RADIX, n_blocks] */
                   __global ulong *keys_out,       /* [n] */
                   __global int *vals_out,         /* [n] */
                   __global const int *limits,     /* see the top of the file */
                   const int n_at,
                   const int bits_at) {
    __local int pos[RADIX * SORT_WG];              /* [RADIX, SORT_WG] */
    const int l = get_local_id(0);
    const int b = get_group_id(0);
    const int n = keys_sorted(n_keys, limits, n_at);
    const int start = min(n, (b * SORT_WG + l) * items);
    const int end = min(n, start + items);
    if (!pass_moves(shift, limits, bits_at)) {   /* uniform over the launch: no barrier is skipped by some */
        for (int i = start; i < end; ++i) {
            keys_out[i] = keys_in[i];
            vals_out[i] = vals_in[i];
        }
        return;
    }
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
