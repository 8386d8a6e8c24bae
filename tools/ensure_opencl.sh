#!/usr/bin/env bash
# Make sure this machine has an OpenCL device that builds endowave-cl's kernels; run it with the
# environment endowave-cl is installed in active (after `pip install`).
#
# PoCL from PyPI (LLVM 14) cannot build kernels for a CPU its LLVM does not know (AMD Zen 5 and
# newer: "unknown target CPU 'generic'"). The distribution's PoCL targets the CPU by instruction
# set instead, so on such a machine this script installs it (Debian/Ubuntu: pocl-opencl-icd, with
# sudo when not root). On any other machine it only checks and changes nothing.
set -euo pipefail
PY=${PYTHON:-python}

check() {   # prints the device endowave-cl would choose, or why there is none; exit status 0 / 1
    "$PY" - <<'PYEOF'
import sys
from endowave_cl.runtime import OpenCLUnavailable, choose_device
try:
    e = choose_device(None)
except OpenCLUnavailable as ex:
    print(f"ensure_opencl: {ex}")
    sys.exit(1)
print(f"ensure_opencl: {e.label} builds kernels")
PYEOF
}

if out=$(check); then echo "$out"; exit 0; fi
echo "$out"
if ! grep -qi "unknown target cpu" <<<"$out"; then
    echo "ensure_opencl: no OpenCL device builds kernels, and not for a reason this script can fix" >&2
    exit 1
fi
if ! command -v apt-get >/dev/null; then
    echo "ensure_opencl: install another PoCL (your distribution's package, or conda-forge's pocl) where the ICD loader finds it: /etc/OpenCL/vendors, or OCL_ICD_VENDORS" >&2
    exit 1
fi
SUDO=""
if [ "$(id -u)" != 0 ]; then
    if command -v sudo >/dev/null; then SUDO="sudo"; else
        echo "ensure_opencl: run as root, or: apt-get install pocl-opencl-icd" >&2; exit 1
    fi
fi
echo "ensure_opencl: installing the distribution's PoCL (pocl-opencl-icd)"
install() { $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends pocl-opencl-icd >/dev/null; }
install || { $SUDO apt-get update -qq && install; }
check
