/* Tile binning and tile ranges (docs/ARCHITECTURE.md "bin, sort, ranges";
 * host side endowave_cl/ops/binning.py).
 *
 *   bin_counts     entries per Gaussian: tiles_touched for visible ones (radius > 0), else 0
 *   bin_gaussians  per Gaussian, its (key, value) pairs at its offset, tiles of its rect
 *                  row-major; key = (tile_id << 32) | as_uint(depth), value = Gaussian id
 *   tile_ranges    per sorted entry, marks where its tile's run starts and ends */
#include "common.h"

/* counts[i] = radius[i] > 0 ? max(tiles_touched[i], 0) : 0. */
__kernel void bin_counts(__global const int *radius,        /* [N] */
                         __global const int *tiles_touched, /* [N] */
                         const int n,
                         __global int *counts) {            /* [N] */
    const int i = get_global_id(0);
    if (i >= n) return;
    counts[i] = (radius[i] > 0) ? max(tiles_touched[i], 0) : 0;
}

/* offsets [N + 1]: exclusive scan of counts followed by the total M.  Gaussian i owns
 * entries [offsets[i], offsets[i + 1]); it writes at most that many (a rect larger than
 * tiles_touched is cut short rather than overrunning its neighbour). */
__kernel void bin_gaussians(__global const int *rect,     /* [N, 4] x0, y0, x1, y1 (exclusive) */
                            __global const float *depth,  /* [N] */
                            __global const int *radius,   /* [N] */
                            __global const int *offsets,  /* [N + 1] */
                            const int n,
                            const int tiles_x,
                            __global ulong *keys,         /* [M] */
                            __global int *values) {       /* [M] */
    const int i = get_global_id(0);
    if (i >= n) return;
    if (radius[i] <= 0) return;
    int k = offsets[i];
    const int end = offsets[i + 1];
    const ulong dbits = (ulong)as_uint(depth[i]);
    const int x0 = rect[4 * i + 0], y0 = rect[4 * i + 1];
    const int x1 = rect[4 * i + 2], y1 = rect[4 * i + 3];
    for (int ty = y0; ty < y1; ++ty) {
        for (int tx = x0; tx < x1; ++tx) {
            if (k >= end) return;
            const ulong tile = (ulong)(ty * tiles_x + tx);
            keys[k] = (tile << 32) | dbits;
            values[k] = i;
            ++k;
        }
    }
}

/* ranges [n_tiles, 2] must be zero on entry.  For sorted entry k of tile t: if k starts
 * t's run, ranges[t].start = k; if it ends it, ranges[t].end = k + 1.  Each slot is written
 * by exactly one work-item.  Entries with tile >= n_tiles are ignored. */
__kernel void tile_ranges(__global const ulong *sorted_keys, /* [M] */
                          const int m,
                          const int n_tiles,
                          __global int *ranges) {            /* [n_tiles, 2] */
    const int k = get_global_id(0);
    if (k >= m) return;
    const uint tile = (uint)(sorted_keys[k] >> 32);
    const uint prev = (k > 0) ? (uint)(sorted_keys[k - 1] >> 32) : 0xFFFFFFFFu;
    const uint next = (k + 1 < m) ? (uint)(sorted_keys[k + 1] >> 32) : 0xFFFFFFFFu;
    if (tile >= (uint)n_tiles) return;
    if (tile != prev) ranges[2 * tile + 0] = k;
    if (tile != next) ranges[2 * tile + 1] = k + 1;
}
