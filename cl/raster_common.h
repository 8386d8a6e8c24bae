/* Code shared by the four rasterizer kernels: rasterize.cl / rasterize_bwd.cl (one pixel per
 * work-item, the GPU path) and rasterize_vec.cl / rasterize_vec_bwd.cl (a block of VW pixels per
 * work-item in floatVW lanes, the CPU path).  OpenCL C 1.2.
 *
 *   EXP_NONPOS_BODY   the exp(x <= 0) polynomial, written once for float and floatVW (exp_poly.h)
 *   TileWork          a work-item's place in its tile's work-group and its pixel block
 *   group_max_last    the largest `last` of a tile (how far back the adjoints walk)
 *   add_gradient      the atomic add of one of a Gaussian's NV gradient values
 *   RASTER_*_ARGS     the kernel arguments the variants share
 */
#ifndef ENDOWAVE_RASTER_COMMON_H
#define ENDOWAVE_RASTER_COMMON_H
#include "common.h"

#include "exp_poly.h"   /* EXP_NONPOS_BODY, exp_nonpos */

/* One work-group per screen tile; work-item (lx, ly) of a (TILE / bw) x (TILE / bh) group owns the
 * bw x bh pixel block whose first pixel is (x0, y0) (bw = bh = 1: one pixel per work-item). */
typedef struct {
    int lx, ly, lid;        /* local id, and its row-major flat index */
    int tx, ty, tile;       /* the tile, and its row-major index */
    int x0, y0;             /* the block's first pixel */
    float px0, py0;         /* its centre (pixel (i, j) has centre (i + 0.5, j + 0.5)) */
} TileWork;

inline TileWork tile_work(int bw, int bh, int tiles_x) {
    TileWork w;
    w.lx = get_local_id(0); w.ly = get_local_id(1);
    w.lid = w.ly * (TILE / bw) + w.lx;
    w.tx = get_group_id(0); w.ty = get_group_id(1);
    w.tile = w.ty * tiles_x + w.tx;
    w.x0 = w.tx * TILE + w.lx * bw; w.y0 = w.ty * TILE + w.ly * bh;
    w.px0 = (float)w.x0 + 0.5f; w.py0 = (float)w.y0 + 0.5f;
    return w;
}

/* The largest of the work-items' `mine` (their pixels' last contributors), uniform over the group:
 * the adjoints walk the tile's list from there down to entry 0.  Every work-item must call it. */
inline int group_max_last(int mine, int lid, __local int *l_max_last) {
    if (lid == 0) *l_max_last = 0;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (mine > 0) atomic_max(l_max_last, mine);
    barrier(CLK_LOCAL_MEM_FENCE);
    return *l_max_last;
}

/* Adds v to gradient value k of Gaussian g: k < 2 the mean, < 5 the conic, 5 the opacity, then the
 * C features (the NV = 6 + C values of the adjoints' per-entry terms).  Skipped when v is 0. */
inline void add_gradient(int k, int g, float v, volatile __global float *v_means2d,
                         volatile __global float *v_conic, volatile __global float *v_opac,
                         volatile __global float *v_features) {
    if (v == 0.0f) return;
    volatile __global float *dst =
        k < 2 ? v_means2d + 2 * g + k :
        k < 5 ? v_conic + 3 * g + (k - 2) :
        k == 5 ? v_opac + g : v_features + g * C + (k - 6);
    atomic_add_global_f(dst, v);
}

/* Kernel arguments shared by the variants: the sorted list and the image (after the per-Gaussian
 * inputs), the forward's outputs, and the adjoints' inputs and outputs. */
#define RASTER_LIST_ARGS                                                                   \
    __global const int *sorted_values,  /* [M] Gaussian ids, tile-major then depth */     \
    __global const int2 *tile_ranges,   /* [n_tiles] (start, end) */                      \
    const int width, const int height, const int tiles_x
#define RASTER_FWD_OUT_ARGS                                                                \
    __global float *out,                /* [H, W, C] */                                   \
    __global float *alpha_out,          /* [H, W] */                                      \
    __global float *t_final,            /* [H, W] */                                      \
    __global int *last_out              /* [H, W] */
#define RASTER_BWD_ARGS                                                                    \
    __global const float *t_final,      /* [H, W] */                                      \
    __global const int *last_in,        /* [H, W] */                                      \
    __global const float *v_out,        /* [H, W, C] */                                   \
    __global const float *v_alpha,      /* [H, W] */                                      \
    volatile __global float *v_means2d, /* [N, 2]  accumulated (+=) */                    \
    volatile __global float *v_conic,   /* [N, 3] */                                      \
    volatile __global float *v_opac,    /* [N] */                                         \
    volatile __global float *v_features,/* [N, C] */                                      \
    __global float *v_entry             /* [M, NV] per sorted entry (DETERMINISTIC only) */

/* The local arrays of a batch of n staged Gaussians (all four kernels; each adds its own). */
#define RASTER_BATCH_LOCALS(n)                                                             \
    __local float2 l_mean[n];                                                              \
    __local float4 l_cop[n];            /* (a, b, c, opac) */                              \
    __local float l_feat[(n) * C];                                                         \
    __local float l_thr[n]              /* power threshold of the early skip */

#endif
