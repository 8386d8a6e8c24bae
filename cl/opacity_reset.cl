/* The 3DGS opacity reset, in place on the device (endowave_cl/ops/adam.py opacity_reset;
 * reference: endowave_cl/reference/adam.py opacity_reset_ref).
 *
 * opacity [n] holds logits; cap = logit(opacity_reset_value).  opacity[i] = min(opacity[i], cap):
 * written only where it is above the cap, so a NaN stays NaN (as numpy's minimum). */
__kernel void opacity_reset(__global float *opacity, const float cap, const int n) {
    const int i = get_global_id(0);
    if (i < n && opacity[i] > cap) opacity[i] = cap;
}
