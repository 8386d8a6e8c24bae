/* exp(x) for x <= 0 on OpenCL vectors (floatVW, VW a build option: 2, 4, 8 or 16), in plain
 * arithmetic so that it stays inline and SIMD on CPU drivers (PoCL calls builtin exp out of line).
 * Lane for lane the same operations, in the same order, as exp_nonpos in rasterize.cl, so both
 * give bit-identical results: Cody-Waite reduction x = k ln2 + r, |r| <= ln2 / 2, degree-7 Taylor
 * polynomial of e^r (truncation < 1e-8 relative), scaling by 2^k in the exponent bits; about 1 ulp.
 * OpenCL C 1.2. */
#ifndef ENDOWAVE_VEXP_H
#define ENDOWAVE_VEXP_H

#ifndef VW
#define VW 8
#endif

/* floatVW, intVW, vloadVW, vstoreVW, convert_intVW */
#define VCAT_(a, b) a##b
#define VCAT(a, b) VCAT_(a, b)
#define floatV VCAT(float, VW)
#define intV VCAT(int, VW)
#define vloadV VCAT(vload, VW)
#define vstoreV VCAT(vstore, VW)
#define convert_intV VCAT(convert_int, VW)
#define convert_floatV VCAT(convert_float, VW)
#define as_floatV VCAT(as_float, VW)
#define as_intV VCAT(as_int, VW)

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
/* sum of the lanes, pairwise halving (a fixed order) */
inline float vhsum(floatV v) {
#if VW == 16
    const float8 v8 = v.lo + v.hi; const float4 v4 = v8.lo + v8.hi;
#elif VW == 8
    const float4 v4 = v.lo + v.hi;
#elif VW == 4
    const float4 v4 = v;
#endif
#if VW == 2
    return v.x + v.y;
#else
    const float2 v2 = v4.lo + v4.hi;
    return v2.x + v2.y;
#endif
}
#define VALL(m) (vred_and(m) != 0)    /* every lane true */
#define VANY(m) (vred_or(m) != 0)     /* some lane true */

#define VEXP_FLOOR (-80.0f)
#define VEXP_LN2_HI 0.693145751953125f           /* ln 2 split so that k * LN2_HI is exact */
#define VEXP_LN2_LO 1.428606765330187045e-06f
#define VEXP_LOG2E 1.44269504088896341f

inline floatV vexp_nonpos(floatV x) {
    x = x < (floatV)(VEXP_FLOOR) ? (floatV)(VEXP_FLOOR) : x;
    const intV k = convert_intV(x * VEXP_LOG2E - 0.5f);  /* round toward zero = to nearest, x <= 0 */
    const floatV kf = convert_floatV(k);
    const floatV r = (x - kf * VEXP_LN2_HI) - kf * VEXP_LN2_LO;
    floatV p = (floatV)(1.0f / 5040.0f);
    p = p * r + 1.0f / 720.0f;
    p = p * r + 1.0f / 120.0f;
    p = p * r + 1.0f / 24.0f;
    p = p * r + 1.0f / 6.0f;
    p = p * r + 0.5f;
    p = p * r + 1.0f;
    p = p * r + 1.0f;
    return as_floatV(as_intV(p) + (k << 23));
}

#endif
