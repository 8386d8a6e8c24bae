/* Tile binning and tile ranges (docs/ARCHITECTURE.md "bin, sort, ranges";
 * host side endowave_cl/ops/binning.py).
 *
 *   bin_counts     entries per Gaussian: tiles_touched for visible ones (radius > 0), else 0
 *   bin_gaussians  per Gaussian, its (key, value) pairs at its offset, tiles of its rect
 *                  row-major; key = (tile_id << 32) | as_uint(depth), value = Gaussian id
 *   tile_ranges    per sorted entry, marks where its tile's run starts and ends
 *   depth_keys, counts_in_order, bin_in_order
 *                  bin_and_sort's two-stage order: the Gaussians sorted by depth first, their
 *                  entries then emitted in that order with the tile alone as the key
 *
 * bin_and_sort keeps what it learns on the device: the depth bounds (bin_counts -> depth_keys,
 * which also writes the depth sort's key bits) and the pair count M (offsets[N]), which
 * bin_in_order and tile_ranges compare with the capacity C of the pair buffers: entries at or past
 * C are not written, and an overflowed list (M > C) has no tile ranges (the host re-runs it). */
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
        const int tt = tiles_touched[i];
        const int c = (radius[i] > 0 && tt > 0) ? tt : 0;
        counts[i] = c;
        if (c > 0) { lo = as_uint(depth[i]); hi = lo; }
    }
    l_lo[l] = lo; l_hi[l] = hi;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (l == 0) {
        /* selects, not min / max: PoCL calls those out of line */
        for (int k = 1; k < BIN_WG; k++) {
            lo = l_lo[k] < lo ? l_lo[k] : lo;
            hi = l_hi[k] > hi ? l_hi[k] : hi;
        }
        if (lo <= hi) {
            atomic_min(&dbounds[0], lo);
            atomic_max(&dbounds[1], hi);
        }
    }
}

/* The entries of Gaussian g at k .. end - 1, the tiles of its rect row-major: key (tile << shift) |
 * low, value g.  It writes at most end - k of them (a rect larger than its count is cut short
 * rather than overrunning the next Gaussian's entries). */
inline void emit_entries(__global const int *rect, const int g, int k, const int end, const int tiles_x,
                         const int shift, const ulong low, __global ulong *keys, __global int *values) {
    const int x0 = rect[4 * g + 0], y0 = rect[4 * g + 1];
    const int x1 = rect[4 * g + 2], y1 = rect[4 * g + 3];
    for (int ty = y0; ty < y1; ++ty) {
        for (int tx = x0; tx < x1; ++tx) {
            if (k >= end) return;
            keys[k] = ((ulong)(ty * tiles_x + tx) << shift) | low;
            values[k] = g;
            ++k;
        }
    }
}

/* offsets [N + 1]: exclusive scan of counts followed by the total M.  Gaussian i owns entries
 * [offsets[i], offsets[i + 1]), key (tile << 32) | as_uint(depth). */
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
    emit_entries(rect, i, offsets[i], offsets[i + 1], tiles_x, 32, (ulong)as_uint(depth[i]), keys, values);
}

/* ranges [n_tiles, 2] must be zero on entry.  For sorted entry k of tile t = key >> shift: if k
 * starts t's run, ranges[t].start = k; if it ends it, ranges[t].end = k + 1.  Each slot is written
 * by exactly one work-item.  Entries with tile >= n_tiles are ignored.
 * The entries are the first m_cap, or, where m_at >= 0, the first count[m_at] (the pair count on
 * the device); a count above m_cap (the list overflowed its buffers) writes no range at all. */
__kernel void tile_ranges(__global const ulong *sorted_keys, /* [m_cap] */
                          const int m_cap,
                          const int n_tiles,
                          const int shift,
                          __global int *ranges,              /* [n_tiles, 2] */
                          __global const int *count,         /* [> m_at] or any buffer (m_at < 0) */
                          const int m_at) {
    const int k = get_global_id(0);
    const int m = m_at < 0 ? m_cap : count[m_at];
    if (k >= m || m > m_cap) return;
    const uint tile = (uint)(sorted_keys[k] >> shift);
    const uint prev = (k > 0) ? (uint)(sorted_keys[k - 1] >> shift) : 0xFFFFFFFFu;
    const uint next = (k + 1 < m) ? (uint)(sorted_keys[k + 1] >> shift) : 0xFFFFFFFFu;
    if (tile >= (uint)n_tiles) return;
    if (tile != prev) ranges[2 * tile + 0] = k;
    if (tile != next) ranges[2 * tile + 1] = k + 1;
}

/* Stage 1 of bin_and_sort (ops/binning.py): keys[i] = as_uint(depth[i]) - dmin for the Gaussians
 * that have entries (counts[i] > 0; dmin = dbounds[0], their least depth pattern, or 0 where none
 * has), 0 for the others (they emit nothing, so where they sort does not matter); ids[i] = i.  A
 * stable sort of these keys gives the Gaussians in depth order, equal depths in id order.
 * key_bits[0] = the bits those keys span, bit_length(dbounds[1] - dbounds[0]) (0 where none has
 * entries): the sort's passes above them copy (cl/sort.cl limits). */
__kernel void depth_keys(__global const float *depth,     /* [N] */
                         __global const int *counts,      /* [N] bin_counts */
                         const int n,
                         __global const uint *dbounds,    /* [2] bin_counts' (min, max) */
                         __global ulong *keys,            /* [N] */
                         __global int *ids,               /* [N] */
                         __global int *key_bits) {        /* [1] */
    const int i = get_global_id(0);
    const uint lo = dbounds[0], hi = dbounds[1];
    const uint dmin = lo <= hi ? lo : 0u;
    if (i == 0) key_bits[0] = lo <= hi ? 32 - (int)clz(hi - lo) : 0;
    if (i >= n) return;
    keys[i] = counts[i] > 0 ? (ulong)(as_uint(depth[i]) - dmin) : 0ul;
    ids[i] = i;
}

/* counts_r[r] = counts[order[r]]: the entry counts in depth order (their scan places the entries) */
__kernel void counts_in_order(__global const int *order,    /* [N] Gaussian ids in depth order */
                              __global const int *counts,   /* [N] */
                              const int n,
                              __global int *counts_r) {     /* [N] */
    const int r = get_global_id(0);
    if (r < n) counts_r[r] = counts[order[r]];
}

#ifndef RECT_AHEAD
#define RECT_AHEAD 16   /* bin_in_order: ranks between a rect's prefetch and its use */
#endif
/* Stage 2: bin_gaussians in depth order.  The Gaussian of rank r (g = order[r]) writes its entries
 * at offsets_r[r] .. offsets_r[r + 1], the tiles of its rect row-major, key = tile id, value = g.
 * A stable sort by tile then leaves each tile's entries in depth order, equal depths in id order:
 * the order of sorting (tile << 32 | depth bits) keys emitted in id order.  Entries at or past
 * m_cap (the buffers' length, below M only when the list overflowed) are not written. */
__kernel void bin_in_order(__global const int *rect,       /* [N, 4] x0, y0, x1, y1 (exclusive) */
                           __global const int *order,      /* [N] */
                           __global const int *offsets_r,  /* [N + 1] scan of counts_in_order */
                           const int n,
                           const int tiles_x,
                           const int m_cap,
                           __global ulong *keys,           /* [m_cap] */
                           __global int *values) {         /* [m_cap] */
    const int r = get_global_id(0);
    if (r >= n) return;
#if HAVE_PREFETCH
    /* the rect of the Gaussian RECT_AHEAD ranks on: the ranks visit the rects in depth order,
     * scattered over the array, which the sort's passes have pushed out of the nearer caches */
    if (r + RECT_AHEAD < n) PREFETCH(rect + 4 * order[r + RECT_AHEAD]);
#endif
    const int k = offsets_r[r], end = min(offsets_r[r + 1], m_cap);
    if (k < end) emit_entries(rect, order[r], k, end, tiles_x, 0, 0ul, keys, values);
}
