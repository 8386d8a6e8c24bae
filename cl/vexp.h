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
/* The lane sums of four vectors, (sum a, sum b, sum c, sum d), in one fixed order: each vector is
 * halved to 4 lanes, then adjacent pairs are added across the four at once (two shuffled adds
 * instead of the 3 x 4 of four separate reductions). */
inline float4 vhsum4(floatV a, floatV b, floatV c, floatV d) {
#if VW == 2
    return (float4)(a.x + a.y, b.x + b.y, c.x + c.y, d.x + d.y);
#else
#if VW == 16
    const float8 a8 = a.lo + a.hi, b8 = b.lo + b.hi, c8 = c.lo + c.hi, d8 = d.lo + d.hi;
    const float4 a4 = a8.lo + a8.hi, b4 = b8.lo + b8.hi, c4 = c8.lo + c8.hi, d4 = d8.lo + d8.hi;
#elif VW == 8
    const float4 a4 = a.lo + a.hi, b4 = b.lo + b.hi, c4 = c.lo + c.hi, d4 = d.lo + d.hi;
#else
    const float4 a4 = a, b4 = b, c4 = c, d4 = d;
#endif
    const float8 ab = (float8)(a4, b4), cd = (float8)(c4, d4);
    const float8 p = (float8)(ab.even + ab.odd, cd.even + cd.odd);   /* 2 partial sums per vector */
    return p.even + p.odd;
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
