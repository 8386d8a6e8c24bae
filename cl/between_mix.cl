/* The in-between target's last step (endowave_cl/ops/between.py between_mix; reference:
 * endowave_cl/reference/between.py between_mix_ref, the host path train/between.py
 * blend_model_prediction's end): the flow prediction blended with the model's,
 * image = wf flow + wm model (wf = 1 - model_weight, wm = model_weight, rounded on the host), and
 * the supervision weight times the model warp's ok.  count [1] (int, zero before the launch)
 * gains the number of pixels whose weight is above 0, per work-group through local memory.  The
 * flow-only target counts its pixels with the same kernel, wm = 0 and ok absent (has_ok 0) giving
 * image = flow and weight unchanged.  No adjoint. */
#pragma OPENCL FP_CONTRACT OFF

__kernel void between_mix(__global const float *flow, __global const float *model, const float wf, const float wm,
                          __global const float *weight_in, __global const float *ok, const int has_ok, const int n,
                          __global float *image, __global float *weight, __global int *count,
                          __local int *group_count) {
    const int i = get_global_id(0);
    if (get_local_id(0) == 0) *group_count = 0;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (i < n) {
        const float w = has_ok ? weight_in[i] * ok[i] : weight_in[i];
        if (wm != 0.0f) vstore3(vload3(i, flow) * wf + vload3(i, model) * wm, i, image);
        else vstore3(vload3(i, flow), i, image);
        weight[i] = w;
        if (w > 0.0f) atomic_inc(group_count);
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (get_local_id(0) == 0 && *group_count) atomic_add(count, *group_count);
}
