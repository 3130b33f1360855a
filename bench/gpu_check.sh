#!/usr/bin/env bash
# The checks and figures that need a CUDA GPU, as one time-boxed run (a lent GPU machine is counted in minutes).
#
#   bash bench/gpu_check.sh OUTDIR [SECONDS]        (default OUTDIR out/gpu, SECONDS 560)
#
# In order, each step time-boxed so that the later ones still run and whatever finished is kept:
#   1. the device: nvidia-smi, Taichi on CUDA;
#   2. the engine's tests on CUDA (FLUIDLAB_TEST_ARCH=cuda, conftest.py): the `cuda` test (every material, a
#      static and a tool against the CPU), the API, liquid, viscous, solid and gas physics tests (GPU_CHECK_TESTS
#      replaces that list, e.g. with tests/test_gradients.py for a longer BUDGET);
#   3. bench/bench_mpm.py on CUDA;
#   4. bench/bench_gas.py on CUDA at 64³ and 128³, PhiFlow beside it on the same GPU (torch CUDA);
#   5. bench/bench_sizes.py at paper size on CUDA (ms per simulated step, forward and gradient);
#   6. bench/bench_gas_fractions.py on CUDA (whole cells against face fractions, 48³ and 64³);
#   7. with time left, a short DP run at paper size (python -m fluidlab_core.benchmark --size paper --arch cuda).
# GPU_CHECK_STEPS chooses the steps and their order (default: device tests mpm gas sizes fractions dp), e.g.
# GPU_CHECK_STEPS="device gas sizes fractions dp tests" takes the figures first and tests with what time is left.
# Everything is streamed to OUTDIR/run.log; the result files (bench/results/*_cuda*, the test report, the DP run)
# are packed into OUTDIR/results.tgz at the end, and Taichi's kernel cache into OUTDIR/ticache_cuda.tgz.
#
# The package's Python dependencies must be importable. Where the machine cannot install them (no network), a
# tarball of them unpacked (.whl/site312.tar.xz, ignored by git; docs/gpu.md says how it is made) is put on
# PYTHONPATH.
set -u
OUT=${1:-out/gpu}
BUDGET=${2:-560}
PY=${PYTHON:-python3}
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
LOG="$OUT/run.log"
T0=$(date +%s)
left() { echo $((BUDGET - ($(date +%s) - T0))); }
say() { echo "[$(($(date +%s) - T0)) s] $*" | tee -a "$LOG"; }
step() {  # step SECONDS NAME COMMAND...: run with a time box no longer than what is left
    local cap=$1 name=$2
    shift 2
    local l
    l=$(left)
    [ "$cap" -gt "$l" ] && cap=$l
    if [ "$cap" -lt 20 ]; then say "SKIP $name (no time left)"; return; fi
    say "START $name (time box $cap s)"
    timeout -k 5 "$cap" "$@" >>"$LOG" 2>&1
    local rc=$?
    # a time box kills the step's own process, not its children (pytest-xdist's workers): without this they go
    # on compiling and running on the CPU and the GPU through every later step and spoil its timings
    # (by process name: matching command lines would also match a shell whose command line names python)
    pkill -9 -x "$(basename "$PY")" 2>/dev/null; sleep 1
    say "END $name rc=$rc"
}

export PYTHONPATH=$PWD
if [ -f .whl/site312.tar.xz ]; then
    mkdir -p /tmp/flsite && tar xJf .whl/site312.tar.xz -C /tmp/flsite && export PYTHONPATH=/tmp/flsite:$PWD
fi
export TI_OFFLINE_CACHE_FILE_PATH=/tmp/fl_ticache
# Compiling dominates a short lease (docs/gpu.md): a Taichi cache brought back by an earlier run (OUTDIR/ticache_cuda.tgz,
# copied to .whl/, which git ignores and the device tool carries when asked) starts this one warm for the kernels
# that have not changed since
if [ -f .whl/ticache_cuda.tgz ]; then
    mkdir -p "$TI_OFFLINE_CACHE_FILE_PATH" && tar xzf .whl/ticache_cuda.tgz -C "$TI_OFFLINE_CACHE_FILE_PATH"
fi
mkdir -p bench/results

run_step() {
    case "$1" in
    device) step 40 device bash -c "nvidia-smi -L; nproc; $PY -c 'import sys, numpy, taichi as ti; ti.init(arch=ti.cuda); \
print(sys.version.split()[0], numpy.__version__, ti.__version__, ti.lang.impl.current_cfg().arch)'" ;;
    # Time boxes from the first run (H200, 2026-11-26): compiling the MPM kernels takes about 42 s on CUDA (11 s
    # on the CPU); 34 of these tests passed in 200 s, the CUDA-against-CPU test and the gradient tests did not finish.
    tests) step 200 tests env FLUIDLAB_TEST_ARCH=cuda $PY -m pytest -p no:cacheprovider -n 12 --dist load -v -rfEs \
        --durations=15 --junitxml="$OUT/tests_cuda.xml" ${GPU_CHECK_TESTS:-tests/test_engine_api.py \
        tests/test_physics_liquids.py tests/test_physics_viscous.py tests/test_physics_solids.py tests/test_gas.py} ;;
    mpm) step 90 mpm_cuda $PY bench/bench_mpm.py --arch cuda --steps 20 --particles 20000 100000 ;;
    gas) step 170 gas $PY bench/bench_gas.py --arch cuda --sizes 64 128 --steps 8 5 --grad-steps 4 2 \
        --phiflow-steps 3 2 --phiflow-grad-steps 2 0 ;;
    sizes) step 170 sizes $PY bench/bench_sizes.py --arch cuda --sizes paper \
        --tasks LatteArtStir GatheringEasy AirCirculation ;;
    fractions) step 90 fractions $PY bench/bench_gas_fractions.py --arch cuda --sizes 48 64 --steps 5 --grad-steps 2 \
        --repeats 1 --solids tool particles ;;
    dp) if [ "$(left)" -gt 100 ]; then
            step $(($(left) - 15)) dp_paper $PY -m fluidlab_core.benchmark --size paper --arch cuda \
                --tasks LatteArtStir --methods dp --seeds 0 --rollouts 8 --checkpoints 2 --jobs 1 --no-ray \
                --out "$OUT/benchmark_paper"
        else say "SKIP dp_paper (no time left)"; fi ;;
    *) say "unknown step $1" ;;
    esac
}
for s in ${GPU_CHECK_STEPS:-device tests mpm gas sizes fractions dp}; do run_step "$s"; done

say "packing"
mkdir -p "$OUT/pack" && cp -r bench/results/*cuda* "$OUT/pack/" 2>/dev/null
for f in tests_cuda.xml benchmark_paper; do [ -e "$OUT/$f" ] && mv "$OUT/$f" "$OUT/pack/"; done
tar czf "$OUT/results.tgz" -C "$OUT/pack" . >>"$LOG" 2>&1 && rm -rf "$OUT/pack"
[ -d "$TI_OFFLINE_CACHE_FILE_PATH" ] && tar czf "$OUT/ticache_cuda.tgz" -C "$TI_OFFLINE_CACHE_FILE_PATH" . >>"$LOG" 2>&1
say "done"
