/* exp(x <= 0) in plain arithmetic, for float and (vexp.h) floatVW.  OpenCL C 1.2.
 * Shared by the rasterizer (raster_common.h, vexp.h) and the vector project4d (project4d_common.h). */
#ifndef ENDOWAVE_EXP_POLY_H
#define ENDOWAVE_EXP_POLY_H

/* exp(x) for x <= 0 in plain arithmetic (no builtin call, so PoCL can inline and vectorise it):
 * Cody-Waite reduction x = k ln2 + r, |r| <= ln2 / 2, then a degree-7 Taylor polynomial of e^r
 * (truncation < 1e-8 relative) and the scaling by 2^k in the exponent bits.  About 1 ulp from
 * the correctly rounded value; x below EXP_FLOOR gives ~e^EXP_FLOOR (alpha far below ALPHA_MIN).
 * (PoCL compiles builtin math such as exp and fmin to out-of-line calls: several times slower.)
 * The body is written once for float and for floatVW (vexp.h): FT / IT the float / int type,
 * TO_INT / TO_FLOAT their conversions, AS_FLOAT / AS_INT the reinterpretations; lane for lane the
 * same operations in the same order, so exp_nonpos and vexp_nonpos agree bit for bit. */
#define EXP_FLOOR (-80.0f)
#define LN2_HI 0.693145751953125f           /* ln 2 split so that k * LN2_HI is exact */
#define LN2_LO 1.428606765330187045e-06f
#define LOG2E 1.44269504088896341f
#define EXP_NONPOS_BODY(FT, IT, TO_INT, TO_FLOAT, AS_FLOAT, AS_INT, x)                     \
    x = x < (FT)(EXP_FLOOR) ? (FT)(EXP_FLOOR) : x;                                         \
    const IT k = TO_INT(x * LOG2E - 0.5f);  /* round to nearest for x <= 0 */              \
    const FT kf = TO_FLOAT(k);                                                             \
    const FT r = (x - kf * LN2_HI) - kf * LN2_LO;                                          \
    FT p = (FT)(1.0f / 5040.0f);                                                           \
    p = p * r + 1.0f / 720.0f;                                                             \
    p = p * r + 1.0f / 120.0f;                                                             \
    p = p * r + 1.0f / 24.0f;                                                              \
    p = p * r + 1.0f / 6.0f;                                                               \
    p = p * r + 0.5f;                                                                      \
    p = p * r + 1.0f;                                                                      \
    p = p * r + 1.0f;                                                                      \
    return AS_FLOAT(AS_INT(p) + (k << 23));

#define EXP_TO_INT_S(v) ((int)(v))
#define EXP_TO_FLOAT_S(v) ((float)(v))
inline float exp_nonpos(float x) {
    EXP_NONPOS_BODY(float, int, EXP_TO_INT_S, EXP_TO_FLOAT_S, as_float, as_int, x)
}

#endif
