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
#ifndef BIN_WG
#define BIN_WG 64   /* work-group size of bin_counts (ops/binning.py LOCAL) */
#endif
__kernel __attribute__((reqd_work_group_size(BIN_WG, 1, 1)))
void bin_counts(__global const int *radius,        /* [N] */
                __global const int *tiles_touched, /* [N] */
                __global const float *depth,       /* [N] */
                const int n,
                __global int *counts,              /* [N] */
                volatile __global uint *dbounds) { /* [2] (min, max) */
    /* the group's bounds by a serial pass of work-item 0 over the group's values (local atomics
     * per work-item cost several times more on PoCL) */
    __local uint l_lo[BIN_WG], l_hi[BIN_WG];
    const int i = get_global_id(0), l = get_local_id(0);
    uint lo = 0xFFFFFFFFu, hi = 0u;
    if (i < n) {
        const int c = (radius[i] > 0) ? max(tiles_touched[i], 0) : 0;
        counts[i] = c;
        if (c > 0) { lo = as_uint(depth[i]); hi = lo; }
    }
    l_lo[l] = lo; l_hi[l] = hi;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (l == 0) {
        for (int k = 1; k < BIN_WG; k++) { lo = min(lo, l_lo[k]); hi = max(hi, l_hi[k]); }
        if (lo <= hi) {
            atomic_min(&dbounds[0], lo);
            atomic_max(&dbounds[1], hi);
        }
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
