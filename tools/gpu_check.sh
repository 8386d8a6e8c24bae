#!/usr/bin/env bash
# Measure endowave-cl on a GPU in one command, on a machine that has the GPU and its driver but
# perhaps no pyopencl:
#
#   1. installs the carried wheels when pyopencl or another requirement (numpy, torch, opencv, ...,
#      pytest) is missing:
#      pip install --no-index --find-links WHEELS ...  (WHEELS: --wheels DIR or $ENDOWAVE_WHEELS),
#      into a new virtual environment that sees the system's packages when PYTHON is not one
#   2. finds the NVIDIA OpenCL driver (libnvidia-opencl.so.1: ldconfig -p, then common paths) and,
#      when no ICD file registers it, writes one into a temporary vendors folder (with copies of
#      the ICD files already registered) and exports OCL_ICD_VENDORS;
#   3. selects the GPU ($ENDOWAVE_CL_DEVICE, --device SPEC; default "nvidia") and prints what the
#      build options are chosen from (runtime.DeviceCaps: SIMT width, sub-groups, local memory,
#      native float atomics);
#   4. runs the kernel test suite on that device, benchmarks/peak_probe.py, benchmarks/perf_table.py,
#      benchmarks/bench_render.py and benchmarks/bench_train_step.py --kernels there (each part's kernel time
#      beside its wall time; on the frames of --scene DIR, else on ../shared's pulling frames when
#      they are beside the checkout, else on a synthetic 640x512 scene), and
#      benchmarks/bench_train_loop.py --both-paths (the schedule's plain and in-between steps, the
#      in-between targets built on the device and on the host; real frames only), and on a GPU
#      (not --quick) the whole default pulling run twice, the loop reading each step's outcome
#      behind the next and the loop waiting at every step ($ENDOWAVE_BLOCKING_STEPS=1);
#   5. writes everything to one report file (--out, default gpu_check_<host>_<date>.txt).
#
# --dry-run: when no GPU is found (or always, with --dry-run), run every step on whatever device
# the defaults choose (PoCL here), saying so in the report, with short benchmark settings: this
# is how the script is checked on machines without a GPU.
#
# --setup-only stops after step 3; --quick uses short benchmark settings; NVIDIA_OPENCL_LIB=PATH
# names the driver library when it is in none of the usual places.
#
#   tools/gpu_check.sh [--wheels DIR] [--device SPEC] [--scene DIR] [--out FILE] [--dry-run] [--quick] [--setup-only]
set -u
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${PYTHON:-python3}"
WHEELS="${ENDOWAVE_WHEELS:-}"
DEVICE="${ENDOWAVE_CL_DEVICE:-}"
OUT=""
SCENE=""
DRY=0
QUICK=0
SETUP_ONLY=0
while [ $# -gt 0 ]; do
    case "$1" in
        --wheels) WHEELS="$2"; shift 2 ;;
        --device) DEVICE="$2"; shift 2 ;;
        --scene) SCENE="$2"; shift 2 ;;
        --out) OUT="$2"; shift 2 ;;
        --dry-run) DRY=1; shift ;;
        --quick) QUICK=1; shift ;;
        --setup-only) SETUP_ONLY=1; shift ;;
        -h|--help) awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' "$0"; exit 0 ;;
        *) echo "gpu_check.sh: unknown argument $1 (see --help)" >&2; exit 2 ;;
    esac
done
[ -n "$OUT" ] || OUT="$ROOT/gpu_check_$(hostname)_$(date +%Y%m%d-%H%M%S).txt"
: > "$OUT" || { echo "gpu_check.sh: cannot write $OUT" >&2; exit 2; }

log() { echo "$*" | tee -a "$OUT"; }
section() { log ""; log "=== $* ($(date -u +%H:%M:%S) UTC, load $(cut -d' ' -f1-3 /proc/loadavg 2>/dev/null))"; }
run() {   # run a command, its output to the terminal and the report, and say how it ended
    log "\$ $*"
    "$@" 2>&1 | tee -a "$OUT"
    local rc=${PIPESTATUS[0]}
    log "(exit status $rc)"
    return $rc
}
FAILED=()

section "endowave-cl GPU check: $ROOT"
log "host: $(hostname), $(nproc) cores, $(uname -sr)"
log "git: $(git -C "$ROOT" log -1 --format='%h %s' 2>/dev/null || echo 'not a git checkout')"
if command -v nvidia-smi >/dev/null 2>&1; then
    nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv 2>&1 | tee -a "$OUT"
else
    log "nvidia-smi: not found"
fi

# ---- 1. Python packages --------------------------------------------------------------------------
section "1. Python packages"
# module:distribution of what the kernels, tests and benchmarks import (setup.cfg install_requires
# and the test extra; PoCL is not needed on a GPU machine)
PKGS="numpy:numpy pyopencl:pyopencl torch:torch cv2:opencv-contrib-python-headless skimage:scikit-image
      matplotlib:matplotlib tqdm:tqdm pywt:pywavelets pytest:pytest hypothesis:hypothesis"
missing=()
for pair in $PKGS; do
    "$PY" -c "import ${pair%%:*}" >/dev/null 2>&1 || missing+=("${pair#*:}")
done
if [ ${#missing[@]} -eq 0 ]; then
    log "all present ($("$PY" -c 'import pyopencl; print("pyopencl", pyopencl.VERSION_TEXT)'))"
elif [ -n "$WHEELS" ] && [ -d "$WHEELS" ]; then
    log "missing: ${missing[*]}; installing from the carried wheels in $WHEELS"
    if "$PY" -c 'import sys; sys.exit(sys.prefix != sys.base_prefix)'; then
        # not a virtual environment (a system Python may refuse pip installs, PEP 668): make one
        # that sees the system's packages, and install the missing ones there
        VENV="${ENDOWAVE_GPU_VENV:-${TMPDIR:-/tmp}/endowave-gpu-venv}"
        run "$PY" -m venv --system-site-packages "$VENV" && PY="$VENV/bin/python"
        log "using the virtual environment $VENV"
    fi
    run "$PY" -m pip install --no-index --find-links "$WHEELS" "${missing[@]}" || FAILED+=("pip install")
else
    log "missing: ${missing[*]} and no wheel folder (--wheels DIR or \$ENDOWAVE_WHEELS): not installed"
fi
"$PY" -c "import pyopencl" >/dev/null 2>&1 || { log "pyopencl is required and not importable: stopping"; exit 1; }
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"

# ---- 2. the NVIDIA OpenCL driver and its ICD file --------------------------------------------------
section "2. OpenCL driver"
LIB="${NVIDIA_OPENCL_LIB:-}"   # an explicit path wins (drivers installed in odd places)
[ -n "$LIB" ] || LIB=$(ldconfig -p 2>/dev/null | awk '/libnvidia-opencl\.so\.1/ {print $NF; exit}')
if [ -z "$LIB" ]; then
    for d in /usr/lib/x86_64-linux-gnu /usr/lib64 /usr/lib /usr/local/nvidia/lib64 /usr/local/nvidia/lib \
             /usr/lib/nvidia /usr/lib/aarch64-linux-gnu /usr/local/cuda/lib64 /run/nvidia/driver/usr/lib/x86_64-linux-gnu; do
        if [ -e "$d/libnvidia-opencl.so.1" ]; then LIB="$d/libnvidia-opencl.so.1"; break; fi
    done
fi
registered=0
for d in ${OCL_ICD_VENDORS:-} /etc/OpenCL/vendors; do
    [ -d "$d" ] && grep -qs "libnvidia-opencl" "$d"/*.icd && registered=1
done
if [ -z "$LIB" ]; then
    log "libnvidia-opencl.so.1: not found (ldconfig -p and the usual folders)"
elif [ $registered -eq 1 ]; then
    log "libnvidia-opencl.so.1: $LIB, already registered by an ICD file"
else
    VENDORS="$(mktemp -d "${TMPDIR:-/tmp}/endowave-icd.XXXXXX")"
    for d in ${OCL_ICD_VENDORS:-} /etc/OpenCL/vendors "$("$PY" -c 'import sys; print(sys.prefix)')/etc/OpenCL/vendors"; do
        [ -d "$d" ] && cp -n "$d"/*.icd "$VENDORS"/ 2>/dev/null
    done
    echo "$LIB" > "$VENDORS/nvidia.icd"
    export OCL_ICD_VENDORS="$VENDORS"
    log "libnvidia-opencl.so.1: $LIB, not registered: wrote $VENDORS/nvidia.icd, OCL_ICD_VENDORS=$VENDORS"
fi

# ---- 3. the device ------------------------------------------------------------------------------
section "3. Device"
run "$PY" -m endowave_cl devices || true
[ -n "$DEVICE" ] || DEVICE="nvidia"
if "$PY" -c "from endowave_cl.runtime import choose_device; import sys; sys.exit(0 if choose_device('$DEVICE').is_gpu else 1)" >/dev/null 2>&1; then
    log "GPU selected by '$DEVICE'"
    GPU=1
else
    GPU=0
    if [ $DRY -eq 1 ]; then
        log "DRY RUN: no GPU matches '$DEVICE'; every step below runs on the default device instead,"
        log "so its figures are NOT GPU figures"
        DEVICE=""
    else
        log "no GPU matches '$DEVICE' (see the list above); pass --device SPEC, or --dry-run to check the script on the default device"
        exit 1
    fi
fi
[ $DRY -eq 1 ] && [ $GPU -eq 1 ] && log "DRY RUN on a GPU: short settings"
if [ -n "$DEVICE" ]; then export ENDOWAVE_CL_DEVICE="$DEVICE"; else unset ENDOWAVE_CL_DEVICE; fi
run "$PY" - <<'EOF' || FAILED+=("device caps")
from endowave_cl.runtime import get_runtime
rt = get_runtime()
print("device:", rt.describe())
print("caps:", rt.caps)
print("build options every kernel gets:", " ".join(rt._options([])[2:]))
from endowave_cl.ops.rasterize import raster_choice
from endowave_cl.ops.sort import GPU_SMALL_MAX, default_config
small, large = default_config(rt, GPU_SMALL_MAX - 1), default_config(rt)
print("rasterizer:", raster_choice(rt, 6).describe(), "| sort:", large if small == large else
      f"{small} below {GPU_SMALL_MAX} keys, {large} from there")
EOF

if [ $SETUP_ONLY -eq 1 ]; then
    section "done (--setup-only: packages, driver and device checked; no tests or benchmarks)"
    log "report: $OUT"
    [ ${#FAILED[@]} -eq 0 ]; exit $?
fi

# ---- 4. tests and benchmarks -------------------------------------------------------------------
if [ $DRY -eq 1 ]; then RUNS=3; STEPS=3; N=20000; else RUNS=7; STEPS=10; N=100000; fi
[ $QUICK -eq 1 ] && { RUNS=3; STEPS=3; }
KERNEL_TESTS=(tests/kernels/test_project4d.py tests/kernels/test_rasterize.py tests/kernels/test_binning.py
              tests/kernels/test_scan_sort.py tests/kernels/test_render.py tests/kernels/test_adam.py
              tests/kernels/test_device_losses.py tests/kernels/test_wavelet.py tests/kernels/test_wavelet_loss.py
              tests/kernels/test_util_ops.py tests/host/test_runtime.py tests/kernels/test_select.py
              tests/kernels/test_between_kernels.py)
section "4a. Kernel tests on the selected device"
( cd "$ROOT" && run "$PY" -m pytest -q -ra -p no:cacheprovider "${KERNEL_TESTS[@]}" ) || FAILED+=("kernel tests")
section "4b. Peaks (benchmarks/peak_probe.py)"
PEAKS="$(mktemp "${TMPDIR:-/tmp}/endowave-peaks.XXXXXX.json")"
run "$PY" "$ROOT/benchmarks/peak_probe.py" --runs 5 --mib $([ $DRY -eq 1 ] && echo 64 || echo 512) --json "$PEAKS" || FAILED+=("peak_probe")
section "4c. Per-kernel table (benchmarks/perf_table.py)"
run "$PY" "$ROOT/benchmarks/perf_table.py" --runs "$RUNS" --n "$N" --peaks "$PEAKS" \
    --png "${OUT%.txt}_roofline.png" || FAILED+=("perf_table")
section "4d. benchmarks/bench_render.py"
run "$PY" "$ROOT/benchmarks/bench_render.py" --runs "$RUNS" --n "$N" --no-reference || FAILED+=("bench_render")
[ $GPU -eq 1 ] && { run "$PY" "$ROOT/benchmarks/bench_render.py" --runs "$RUNS" --n "$N" --no-reference --adjoint-mode deterministic || FAILED+=("bench_render deterministic"); }
section "4e. benchmarks/bench_train_step.py"
SCENE_ARGS=()
if [ -n "$SCENE" ]; then
    if [ -f "$SCENE/poses_bounds.npy" ]; then SCENE_ARGS=(--scene "$SCENE")
    else log "--scene $SCENE: no poses_bounds.npy there; bench_train_step uses its default scene"; fi
fi
run "$PY" "$ROOT/benchmarks/bench_train_step.py" --kernels --runs "$STEPS" --warmup 2 --gaussians "$N" ${SCENE_ARGS[@]+"${SCENE_ARGS[@]}"} \
    || FAILED+=("bench_train_step")
section "4f. benchmarks/bench_train_loop.py (the schedule's steps per kind; in-between targets on the device and on the host)"
run "$PY" "$ROOT/benchmarks/bench_train_loop.py" --both-paths --steps $((STEPS * 4)) ${SCENE_ARGS[@]+"${SCENE_ARGS[@]}"} \
    || FAILED+=("bench_train_loop")
if [ $GPU -eq 1 ] && [ $DRY -eq 0 ] && [ $QUICK -eq 0 ]; then
    section "4g. The default pulling run, each step's outcome read behind the next, then waiting at every step"
    run "$PY" "$ROOT/benchmarks/bench_train_loop.py" --steps 1 --warmup 0 --full-run --blocking-too \
        ${SCENE_ARGS[@]+"${SCENE_ARGS[@]}"} || FAILED+=("bench_train_loop --full-run")
fi

section "done"
if [ ${#FAILED[@]} -eq 0 ]; then
    log "every step passed; report: $OUT"
    exit 0
fi
log "steps that failed: ${FAILED[*]}; report: $OUT"
exit 1
