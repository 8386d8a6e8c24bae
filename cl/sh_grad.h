/* The TEASH colour's sizes, and the gradient of its SH coefficients in factored form (OpenCL C 1.2).
 * Included by project4d_common.h (project4d, project4d_bwd) and adam.cl.
 *
 * A Gaussian's colour is max(0, 0.5 + sum_f cos_f sum_k c[f, k, rgb] Y_k), so the gradient of its
 * SH coefficients is an outer product of per-Gaussian factors:
 *     v_sh[f, k, c] = (gcol_c Y_k) cos_f
 * with gcol_c the colour gradient where the clamp passes it (else 0), Y_k the SH basis at the view
 * direction and cos_f = cos(omega_f t + phi_f) (cos_0 = 1).  project4d_bwd built with
 * -DP4_SH_FACTORS stores these SHF_SIZE factors per Gaussian instead of the SH_NCOEF products (all
 * zero for a culled Gaussian), and Adam forms the products with sh_grad_expand: the same two
 * multiplications as the full path of project4d_bwd, so the same bits.  Mirrored by
 * endowave_cl/ops/project.py (ShGradFactors). */
#ifndef ENDOWAVE_SH_GRAD_H
#define ENDOWAVE_SH_GRAD_H

#ifndef SH_DEGREE
#define SH_DEGREE 3
#endif
#define SH_K ((SH_DEGREE + 1) * (SH_DEGREE + 1))   /* SH bases per temporal frequency */
#ifndef NT
#define NT 2
#endif
#define SH_NCOEF ((NT + 1) * SH_K * 3)   /* SH coefficients per Gaussian, [NT+1, SH_K, 3] */

/* a Gaussian's row of factors, [SHF_SIZE]: cos_f (f = 0..NT), gcol_c (c = 0..2), Y_k (k = 0..SH_K-1) */
#define SHF_COS 0
#define SHF_GCOL (NT + 1)
#define SHF_Y (NT + 4)
#define SHF_SIZE (NT + 4 + SH_K)

/* g [SH_NCOEF] (e = f SH_K 3 + 3 k + c) of one Gaussian from its factors fac [SHF_SIZE] */
inline void sh_grad_expand(const float *fac, float *g) {
    float gY[SH_K * 3];   /* gcol_c Y_k, shared by every frequency */
    for (int k = 0; k < SH_K; ++k)
        for (int c = 0; c < 3; ++c) gY[3 * k + c] = fac[SHF_GCOL + c] * fac[SHF_Y + k];
    for (int f = 0; f <= NT; ++f)
        for (int j = 0; j < SH_K * 3; ++j) g[f * SH_K * 3 + j] = gY[j] * fac[SHF_COS + f];
}

#endif
