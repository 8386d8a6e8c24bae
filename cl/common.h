/* Shared definitions for every endowave-cl kernel.  OpenCL C 1.2. */
#ifndef ENDOWAVE_COMMON_H
#define ENDOWAVE_COMMON_H

/* Screen tiles are TILE x TILE pixels (3DGS / gsplat); one work-group per tile. */
#ifndef TILE
#define TILE 16
#endif
#define TILE_PIXELS (TILE * TILE)

/* 8 consecutive floats at any (float-aligned) address, written element by element: PoCL calls
 * vload8 / vstore8 out of line (a call per access, and the caller's vectors spilled around it),
 * while the compiler merges these element accesses into one unaligned vector access. */
inline float8 load8(__global const float *p) {
    return (float8)(p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7]);
}

inline void store8(__global float *p, float8 v) {
    p[0] = v.s0; p[1] = v.s1; p[2] = v.s2; p[3] = v.s3;
    p[4] = v.s4; p[5] = v.s5; p[6] = v.s6; p[7] = v.s7;
}

/* The same for 4 floats */
inline float4 load4(__global const float *p) { return (float4)(p[0], p[1], p[2], p[3]); }

inline void store4(__global float *p, float4 v) {
    p[0] = v.x; p[1] = v.y; p[2] = v.z; p[3] = v.w;
}

/* Where the runtime builds with -DHOST_CLANG=1 (DeviceCaps.host_clang: a driver that compiles
 * kernels with clang for the host CPU, PoCL's CPU devices), clang's generic builtins are inline
 * instructions there, while PoCL's own prefetch() does nothing and its sqrt is an out-of-line call
 * (the caller's vectors spilled around it).  Elsewhere the OpenCL builtins.
 *   PREFETCH(p)  a hint to bring the cache line at p closer (prefetcht0 on x86): gathers whose
 *                addresses are known ahead (prefetch_floats: every line of a row; the kernels
 *                that gather scattered rows ask for the row ROWS_AHEAD work-items ahead);
 *   PREFETCH_L2(p) the same hint into the outer caches only (prefetcht1 on x86): blocks of many
 *                lines wanted one work-item later (prefetch_floats_l2), which would evict the
 *                current work-item's lines from L1;
 *   sqrt1, sqrt4, sqrt8 the correctly rounded square root (the same bits as sqrt: LLVM's sqrt, which
 *                PoCL's out-of-line sqrt also runs; lane by lane, which the compiler joins into
 *                one vector instruction);
 *   clz1, clz64  the leading zero bits of a nonzero uint / ulong (one lzcnt / bsr; OpenCL C's
 *                ulong is clang's unsigned long: __builtin_clzll would take a 128-bit long long). */
#ifndef ROWS_AHEAD
#define ROWS_AHEAD 4   /* adam_step_rows, gather_params: work-items between a row's prefetch and its use */
#endif
#if defined(HOST_CLANG) && HOST_CLANG
#define HAVE_PREFETCH 1   /* kernels leave out the loads that only compute prefetch addresses when 0 */
#define PREFETCH(p) __builtin_prefetch(p)
/* every 64-byte line of the n > 0 floats from p */
inline void prefetch_floats(__global const float *p, const int n) {
    for (int c = 0; c < n; c += 16) PREFETCH(p + c);
    PREFETCH(p + n - 1);
}
#define PREFETCH_L2(p) __builtin_prefetch(p, 0, 2)
inline void prefetch_floats_l2(__global const float *p, const int n) {
    for (int c = 0; c < n; c += 16) PREFETCH_L2(p + c);
    PREFETCH_L2(p + n - 1);
}
inline float sqrt1(float x) { return __builtin_sqrtf(x); }
inline int clz1(uint x) { return __builtin_clz(x); }   /* x != 0 */
inline int clz64(ulong x) { return __builtin_clzl(x); }   /* x != 0 */
inline float4 sqrt4(float4 x) {
    return (float4)(__builtin_sqrtf(x.x), __builtin_sqrtf(x.y), __builtin_sqrtf(x.z), __builtin_sqrtf(x.w));
}
inline float8 sqrt8(float8 x) {
    return (float8)(__builtin_sqrtf(x.s0), __builtin_sqrtf(x.s1), __builtin_sqrtf(x.s2),
                    __builtin_sqrtf(x.s3), __builtin_sqrtf(x.s4), __builtin_sqrtf(x.s5),
                    __builtin_sqrtf(x.s6), __builtin_sqrtf(x.s7));
}
#else
#define HAVE_PREFETCH 0
#define PREFETCH(p) ((void)0)
#define PREFETCH_L2(p) ((void)0)
inline float sqrt1(float x) { return sqrt(x); }
inline int clz1(uint x) { return (int)clz(x); }
inline int clz64(ulong x) { return (int)clz(x); }
inline float4 sqrt4(float4 x) { return sqrt(x); }
inline float8 sqrt8(float8 x) { return sqrt(x); }
#endif

/* Add v to a float in global memory.  Where the device has native float atomics
 * (cl_ext_float_atomics with global fp32 add; the runtime then builds with -cl-std=CL2.0 or CL3.0
 * and -DDEVICE_FLOAT_ATOMIC_ADD=1, see DeviceCaps in endowave_cl/runtime.py) this is one relaxed
 * atomic_fetch_add.  Else (OpenCL 1.2 has no float atomics) a compare-and-swap loop on the bit
 * pattern.  The value is never read with a plain load (Oclgrind
 * would report a race): the loop starts from the guess 0 and each failed atomic_cmpxchg returns the
 * current bits.  (Reading it first with atomic_or(p, 0) is equivalent but costs a full fence on
 * PoCL: about a third of the CPU adjoint's time.)
 * Callers should first reduce in local memory so that each work-group issues one
 * such add per destination. */
#if defined(DEVICE_FLOAT_ATOMIC_ADD) && DEVICE_FLOAT_ATOMIC_ADD
#pragma OPENCL EXTENSION cl_ext_float_atomics : enable
inline void atomic_add_global_f(volatile __global float *p, float v) {
    atomic_fetch_add_explicit((volatile __global atomic_float *)p, v, memory_order_relaxed,
                              memory_scope_device);
}
#else
inline void atomic_add_global_f(volatile __global float *p, float v) {
    volatile __global int *pi = (volatile __global int *)p;
    int old_bits = 0;  /* a guess: a failed compare-and-swap returns the current value atomically */
    while (1) {
        float newv = as_float(old_bits) + v;
        int prev = atomic_cmpxchg(pi, old_bits, as_int(newv));
        if (prev == old_bits) break;
        old_bits = prev;
    }
}
#endif

/* Deterministic adjoint: the slot, in the unsorted binning order, of Gaussian g's entry for tile
 * (tx, ty).  bin_gaussians (cl/bin.cl) emitted g's entries at offsets[g] .. offsets[g + 1], its
 * rect's tiles row-major, so per-entry terms stored there are in tile order per Gaussian and
 * contiguous; -1 if the slot lies past g's entries (a rect cut short; no such sorted entry). */
inline int binned_slot(__global const int4 *rect, __global const int *offsets, int g, int tx, int ty) {
    const int4 r = rect[g];   /* (x0, y0, x1, y1) exclusive */
    const int u = offsets[g] + (ty - r.y) * (r.z - r.x) + (tx - r.x);
    return u < offsets[g + 1] ? u : -1;
}

/* Same for local memory (used for per-work-group reductions). */
inline void atomic_add_local_f(volatile __local float *p, float v) {
    volatile __local int *pi = (volatile __local int *)p;
    int old_bits = atomic_or(pi, 0);
    while (1) {
        float newv = as_float(old_bits) + v;
        int prev = atomic_cmpxchg(pi, old_bits, as_int(newv));
        if (prev == old_bits) break;
        old_bits = prev;
    }
}

#endif
