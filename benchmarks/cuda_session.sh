#!/usr/bin/env bash
# The GPU checks in one call of a lent GPU machine: the CUDA tests, then the CUDA benchmarks.
#
#   bash benchmarks/cuda_session.sh [STEP ...]   STEP: env build tests ops core compile imu gdh
#                                                posegraph factor_graph tls suite
#                                                (default: env tests ops factor_graph posegraph)
#
# build: the optional C kernels for that machine's Python (setup.py build_ext --inplace), so
# that the host-CPU rows of the benchmarks and the CPU side of the tests run what a user's CPU
# runs; without it they run the tensor code.  TEST_WORKERS (default 0: one process) runs the
# CUDA tests on that many pytest-xdist workers, TESTS_TIMEOUT (default 400) bounds them in
# seconds; POSEGRAPH_BUDGET (default 80) is the pose-graph step's time budget in seconds.
#
# Runs the checkout it lives in (PYTHONPATH, no install) with that machine's python3 and
# torch; extra pure-Python packages (pypose, the peer of bench_core) are read from .gpu_site/
# when present.  Logs and result files go to $OUT/cuda/ (default /tmp/cuda_out) and, after each
# step, into one archive $OUT/cuda_results.tgz, so a run stopped at its time limit keeps the
# steps it finished.
set -u
cd "$(dirname "$0")/.."
ROOT=$PWD
OUT=${OUT:-/tmp/cuda_out}
WORK=$OUT/cuda
mkdir -p "$WORK"
export PYTHONPATH=$ROOT:$ROOT/.gpu_site${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
PY=${PYTHON:-python3}
STEPS=${*:-env tests ops factor_graph posegraph}
# the datasets: tests and benchmarks read ../shared/data; a copy inside the checkout (shared/)
# travels to the GPU machine where ../shared does not
if [ ! -d ../shared ] && [ -d shared ]; then ln -s "$ROOT/shared" ../shared; fi
# suite: the whole CPU test suite under that machine's torch (another version than CI's), on
# 14 workers of one thread each (with torch's default 16 threads per worker two runs did not
# finish in 330 s), stopped after $SUITE_TIMEOUT (default 240) s; peers missing there (gtsam,
# pytorch-kinematics) skip or fail.

pack() { tar -czf "$OUT/cuda_results.tgz" -C "$WORK" . ; }
step() {  # step NAME COMMAND...: runs it, logs to $WORK/NAME.log, prints its status
    local name=$1; shift
    local t0=$SECONDS
    echo "=== $name: $*"
    "$@" > "$WORK/$name.log" 2>&1
    local rc=$?
    echo "=== $name: exit $rc after $((SECONDS - t0)) s"
    tail -n 25 "$WORK/$name.log"
    pack
    return 0
}

for s in $STEPS; do
  case $s in
    env) step env bash -c "nvidia-smi; $PY -c 'import sys, torch, numpy; print(sys.version); \
print(\"torch\", torch.__version__, \"cuda\", torch.version.cuda, torch.cuda.get_device_name()); \
print(\"numpy\", numpy.__version__)'; $PY -c 'import pypose; print(\"pypose\", pypose.__version__)'; \
$PY -c 'import triton; print(\"triton\", triton.__version__)'; \
nproc; $PY -m pytest --version" ;;
    build) step build timeout 120 $PY setup.py build_ext --inplace -j 3 ;;
    tests) step tests timeout "${TESTS_TIMEOUT:-400}" $PY -m pytest tests/test_cuda.py $(ls tests/test_cuda_engine.py 2>/dev/null) \
             -n "${TEST_WORKERS:-0}" -p no:cacheprovider -W ignore::DeprecationWarning -rA --durations=15 ;;
    # the operators on CUDA (their compiled closed forms) against eager code and the peers, and
    # user code that calls them compiled by torch.compile against the same code eager
    ops) step ops timeout 240 $PY benchmarks/bench_compile.py --device cuda --target-s 0.2 --out "$WORK" \
           --cases "operator eager" "operator compiled" "closed form eager" "matrix_exp eager" \
           "fwd+bwd custom eager" "fwd+bwd plain eager" "xi * 2" "pypose" ;;
    # the estimation engine on the device and on the host CPU in the same run
    # the small problems first: sphere2500's host-side sparse solve takes most of the budget
    posegraph) step posegraph timeout $((${POSEGRAPH_BUDGET:-80} + 40)) $PY benchmarks/bench_posegraph.py \
                 --device cuda --repeats 3 --time-budget "${POSEGRAPH_BUDGET:-80}" --problems pose3example-grid.txt w100.graph sphere2500.txt \
                 --out "$WORK/posegraph_cuda" ;;
    factor_graph) step factor_graph timeout 100 $PY benchmarks/bench_factor_graph.py --device cuda --repeats 5 \
                    --time-budget 40 --out "$WORK/factor_graph_cuda" ;;
    # the TLS study's four batched solves, every trial in one batch on the device, and on the host
    tls) step tls timeout 240 $PY benchmarks/bench_tls.py --device cuda --repeats 3 --out "$WORK" ;;
    core) step core $PY benchmarks/bench_core.py --device cuda --skip gtsam --target 0.2 \
            --out "$WORK" --tag core_cuda ;;
    compile) step compile $PY benchmarks/bench_compile.py --device cuda --target-s 0.2 --out "$WORK" ;;
    imu) step imu $PY benchmarks/bench_imu.py --device cuda --target 5 --out-dir "$WORK" ;;
    gdh) step gdh $PY benchmarks/bench_gdh.py --device cuda --target-a 5 --target-b 5 --out-dir "$WORK" ;;
    suite) OMP_NUM_THREADS=1 step suite timeout "${SUITE_TIMEOUT:-240}" $PY -m pytest -q -n 14 -p no:cacheprovider \
             -W ignore::DeprecationWarning -rfEs --tb=short --ignore=tests/test_cuda.py ;;
    *) echo "unknown step $s"; exit 2 ;;
  esac
done
ls -la "$WORK"
