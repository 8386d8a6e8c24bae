"""The flow-interpolation baseline with other OpenCV flow estimators: does a better pseudo ground
truth exist here?  Per test frame, the PSNR of the interpolation (baselines.py: both neighbours
warped to the test time and blended) with DIS (medium preset, the baseline and the trainer's
default), DIS with a finer setting, Farneback and DeepFlow, and the time each took.

    python tools/interp_flows.py SCENE --downscale 2
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np


def _estimators():
    import cv2

    def dis_fine():
        e = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        e.setFinestScale(0)
        e.setGradientDescentIterations(50)
        e.setPatchSize(8)
        e.setPatchStride(3)
        return e.calc
    return {
        "dis (medium)": lambda: cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc,
        "dis (finest scale 0)": dis_fine,
        "farneback": lambda: (lambda a, b, _: cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 5, 15, 5, 7, 1.5, 0)),
        "deepflow": lambda: cv2.optflow.createOptFlow_DeepFlow().calc,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--downscale", type=float, default=1.0)
    a = ap.parse_args(argv)
    from endowave_cl.baselines import mean_interpolation, neighbours, warp_backward
    from endowave_cl.data.flow import to_grey8
    from endowave_cl.data.scene import load_scene
    from endowave_cl.errors import EndowaveError
    from endowave_cl.metrics import psnr
    try:
        sc = load_scene(a.scene, downscale=a.downscale)
    except EndowaveError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"{a.scene} {sc.width}x{sc.height}, test frames {list(sc.test_indices)}; load "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    for name, make in _estimators().items():
        calc = make()
        scores, t0 = [], time.perf_counter()
        for k in sc.test_indices:
            i0, i1, frac = neighbours(sc, k)
            im0, im1 = sc.frames[i0].image, sc.frames[i1].image
            g0, g1 = to_grey8(im0), to_grey8(im1)
            f01, f10 = calc(g0, g1, None), calc(g1, g0, None)
            img = mean_interpolation(warp_backward(im0, f01, frac), warp_backward(im1, f10, 1 - frac), frac)
            scores.append(psnr(img, sc.frames[k].image))
        print(f"{name:22s} mean {np.mean(scores):6.2f} dB  per frame {np.round(scores, 2).tolist()}  "
              f"{time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
