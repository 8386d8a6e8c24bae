/* exp(x) for x <= 0 on OpenCL vectors (floatVW, VW a build option: 2, 4, 8 or 16), in plain
 * arithmetic so that it stays inline and SIMD on CPU drivers (PoCL calls builtin exp out of line).
 * Lane for lane the same operations, in the same order, as exp_nonpos (both are written from
 * EXP_NONPOS_BODY in exp_poly.h), so both give bit-identical results.
 * OpenCL C 1.2. */
#ifndef ENDOWAVE_VEXP_H
#define ENDOWAVE_VEXP_H
#include "exp_poly.h"   /* EXP_NONPOS_BODY */

#ifndef VW
#define VW 8
#endif

/* floatVW, intVW and their converts, loads and stores */
#define VCAT_(a, b) a##b
#define VCAT(a, b) VCAT_(a, b)
#define floatV VCAT(float, VW)
#define intV VCAT(int, VW)
#define as_floatV VCAT(as_float, VW)
#define as_intV VCAT(as_int, VW)

/* Converts, loads and stores of whole vectors (loads and stores on private arrays).  At 16 lanes
 * each is done on two 8-lane halves joined by a vector literal: PoCL 3.0 (LLVM 14) on AVX-512 CPUs
 * aborts while generating code for convert_float16 from int16, convert_int16 from float16 and
 * vstore16, and computes wrong lanes for vload16 (docs/PORTABILITY.md).  Same values lane for lane. */
#if VW == 16
inline int16 vcvt_int16(float16 x) { return (int16)(convert_int8(x.lo), convert_int8(x.hi)); }
inline float16 vcvt_float16(int16 k) { return (float16)(convert_float8(k.lo), convert_float8(k.hi)); }
inline float16 vload_f16(int i, const float *p) { return (float16)(vload8(2 * i, p), vload8(2 * i + 1, p)); }
inline int16 vload_i16(int i, const int *p) { return (int16)(vload8(2 * i, p), vload8(2 * i + 1, p)); }
inline void vstore_f16(float16 v, int i, float *p) { vstore8(v.lo, 2 * i, p); vstore8(v.hi, 2 * i + 1, p); }
inline void vstore_i16(int16 v, int i, int *p) { vstore8(v.lo, 2 * i, p); vstore8(v.hi, 2 * i + 1, p); }
#define convert_intV vcvt_int16
#define convert_floatV vcvt_float16
#define vloadF vload_f16
#define vloadI vload_i16
#define vstoreF vstore_f16
#define vstoreI vstore_i16
#else
#define convert_intV VCAT(convert_int, VW)
#define convert_floatV VCAT(convert_float, VW)
#define vloadF VCAT(vload, VW)      /* floatV from a private float array */
#define vloadI VCAT(vload, VW)      /* intV from a private int array */
#define vstoreF VCAT(vstore, VW)
#define vstoreI VCAT(vstore, VW)
#endif

/* Lane masks are intV with -1 (true) or 0 per lane, as vector comparisons give.  all / any / select
 * are written out (bitwise halving, vector ?:) because PoCL calls the builtins out of line. */
inline int vred_and(intV m) {
#if VW == 16
    const int8 m8 = m.lo & m.hi; const int4 m4 = m8.lo & m8.hi;
#elif VW == 8
    const int4 m4 = m.lo & m.hi;
#elif VW == 4
    const int4 m4 = m;
#endif
#if VW == 2
    return m.x & m.y;
#else
    const int2 m2 = m4.lo & m4.hi;
    return m2.x & m2.y;
#endif
}
inline int vred_or(intV m) {
#if VW == 16
    const int8 m8 = m.lo | m.hi; const int4 m4 = m8.lo | m8.hi;
#elif VW == 8
    const int4 m4 = m.lo | m.hi;
#elif VW == 4
    const int4 m4 = m;
#endif
#if VW == 2
    return m.x | m.y;
#else
    const int2 m2 = m4.lo | m4.hi;
    return m2.x | m2.y;
#endif
}
/* The lane sums of four vectors, (sum a, sum b, sum c, sum d), in one fixed order: two vectors are
 * folded into one at full width (lanes 0..W/2-1 the halves of one, W/2.. of the other), so each
 * step is one add of two shuffles instead of separate reductions per vector. */
inline float4 vhsum4(floatV a, floatV b, floatV c, floatV d) {
#if VW == 2
    return (float4)(a.x + a.y, b.x + b.y, c.x + c.y, d.x + d.y);
#elif VW == 4
    const float8 ab = (float8)(a, b), cd = (float8)(c, d);
    const float8 p = (float8)(ab.even + ab.odd, cd.even + cd.odd);   /* 2 partial sums per vector */
    return p.even + p.odd;
#elif VW == 8
    const float8 ab = (float8)(a.lo, b.lo) + (float8)(a.hi, b.hi);   /* a a a a b b b b */
    const float8 cd = (float8)(c.lo, d.lo) + (float8)(c.hi, d.hi);
    const float8 p = (float8)(ab.even, cd.even) + (float8)(ab.odd, cd.odd);   /* aa bb cc dd */
    return p.even + p.odd;
#else   /* 16 */
    const float16 ab = (float16)(a.lo, b.lo) + (float16)(a.hi, b.hi);   /* 8 partials of a, 8 of b */
    const float16 cd = (float16)(c.lo, d.lo) + (float16)(c.hi, d.hi);
    const float16 p = (float16)(ab.even, cd.even) + (float16)(ab.odd, cd.odd);   /* 4 of a, b, c, d */
    const float8 q = p.even + p.odd;                                    /* 2 of each */
    return q.even + q.odd;
#endif
}
#define VALL(m) (vred_and(m) != 0)    /* every lane true */
#define VANY(m) (vred_or(m) != 0)     /* some lane true */

/* The lane mask m, unchanged, held in 32-bit lanes.  LLVM keeps a mask made only of comparisons as
 * one bit per lane; on x86 without AVX-512 it stores 16 such bits as bytes and converts them back
 * at every select and VANY (about 30 instructions per hit of rasterize_vec_bwd).  An empty asm
 * that takes and returns the mask in vector registers makes it opaque, so the masks stay in
 * 32-bit lanes as the comparisons produce them.  Other targets (and Oclgrind's SPIR) take m as it
 * is. */
inline intV lane_mask(intV m) {
#if defined(__x86_64__) || defined(__i386__)
#if VW == 16
    int8 lo = m.lo, hi = m.hi;
    __asm__("" : "+x"(lo));
    __asm__("" : "+x"(hi));
    return (int16)(lo, hi);
#else
    __asm__("" : "+x"(m));
    return m;
#endif
#else
    return m;
#endif
}

/* exp(x <= 0) on floatVW: the polynomial of raster_common.h, lane for lane (== exp_nonpos) */
inline floatV vexp_nonpos(floatV x) {
    EXP_NONPOS_BODY(floatV, intV, convert_intV, convert_floatV, as_floatV, as_intV, x)
}

#endif
