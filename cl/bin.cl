/* Tile binning and tile ranges (docs/ARCHITECTURE.md "bin, sort, ranges";
 * host side endowave_cl/ops/binning.py).
 *
 *   bin_counts     entries per Gaussian: tiles_touched for visible ones (radius > 0), else 0
 *   bin_gaussians  per Gaussian, its (key, value) pairs at its offset, tiles of its rect
 *                  row-major; key = (tile_id << 32) | as_uint(depth), value = Gaussian id
 *   tile_ranges    per sorted entry, marks where its tile's run starts and ends */
#include "common.h"

/* counts[i] = radius[i] > 0 ? max(tiles_touched[i], 0) : 0, and the least and greatest depth bit
 * pattern (as_uint) of the Gaussians that have entries: dbounds[0] = min, dbounds[1] = max
 * (dbounds must hold (UINT_MAX, 0) on entry; one global atomic per work-group and bound). */
__kernel void bin_counts(__global const int *radius,        /* [N] */
                         __global const int *tiles_touched, /* [N] */
                         __global const float *depth,       /* [N] */
                         const int n,
                         __global int *counts,              /* [N] */
                         volatile __global uint *dbounds) { /* [2] (min, max) */
    __local uint l_min, l_max;
    const int i = get_global_id(0);
    if (get_local_id(0) == 0) { l_min = 0xFFFFFFFFu; l_max = 0u; }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (i < n) {
        const int c = (radius[i] > 0) ? max(tiles_touched[i], 0) : 0;
        counts[i] = c;
        if (c > 0) {
            const uint b = as_uint(depth[i]);
            atomic_min(&l_min, b);
            atomic_max(&l_max, b);
        }
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (get_local_id(0) == 0 && l_min <= l_max) {
        atomic_min(&dbounds[0], l_min);
        atomic_max(&dbounds[1], l_max);
    }
}

/* offsets [N + 1]: exclusive scan of counts followed by the total M.  Gaussian i owns
 * entries [offsets[i], offsets[i + 1]); it writes at most that many (a rect larger than
 * tiles_touched is cut short rather than overrunning its neighbour).
 * key = (tile << dshift) | (as_uint(depth) - dmin): dmin = 0, dshift = 32 give the full key; with
 * dmin the least depth pattern and dshift the bits of (max - min), the keys keep the same order in
 * fewer bits (fewer radix-sort passes). */
__kernel void bin_gaussians(__global const int *rect,     /* [N, 4] x0, y0, x1, y1 (exclusive) */
                            __global const float *depth,  /* [N] */
                            __global const int *radius,   /* [N] */
                            __global const int *offsets,  /* [N + 1] */
                            const int n,
                            const int tiles_x,
                            const uint dmin,
                            const int dshift,
                            __global ulong *keys,         /* [M] */
                            __global int *values) {       /* [M] */
    const int i = get_global_id(0);
    if (i >= n) return;
    if (radius[i] <= 0) return;
    int k = offsets[i];
    const int end = offsets[i + 1];
    const ulong dbits = (ulong)(as_uint(depth[i]) - dmin);
    const int x0 = rect[4 * i + 0], y0 = rect[4 * i + 1];
    const int x1 = rect[4 * i + 2], y1 = rect[4 * i + 3];
    for (int ty = y0; ty < y1; ++ty) {
        for (int tx = x0; tx < x1; ++tx) {
            if (k >= end) return;
            const ulong tile = (ulong)(ty * tiles_x + tx);
            keys[k] = (tile << dshift) | dbits;
            values[k] = i;
            ++k;
        }
    }
}

/* ranges [n_tiles, 2] must be zero on entry.  For sorted entry k of tile t = key >> shift: if k
 * starts t's run, ranges[t].start = k; if it ends it, ranges[t].end = k + 1.  Each slot is written
 * by exactly one work-item.  Entries with tile >= n_tiles are ignored. */
__kernel void tile_ranges(__global const ulong *sorted_keys, /* [M] */
                          const int m,
                          const int n_tiles,
                          const int shift,
                          __global int *ranges) {            /* [n_tiles, 2] */
    const int k = get_global_id(0);
    if (k >= m) return;
    const uint tile = (uint)(sorted_keys[k] >> shift);
    const uint prev = (k > 0) ? (uint)(sorted_keys[k - 1] >> shift) : 0xFFFFFFFFu;
    const uint next = (k + 1 < m) ? (uint)(sorted_keys[k + 1] >> shift) : 0xFFFFFFFFu;
    if (tile >= (uint)n_tiles) return;
    if (tile != prev) ranges[2 * tile + 0] = k;
    if (tile != next) ranges[2 * tile + 1] = k + 1;
}
