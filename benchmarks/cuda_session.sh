#!/usr/bin/env bash
# The GPU checks in one call of a lent GPU machine: the CUDA tests, then the CUDA benchmarks.
#
#   bash benchmarks/cuda_session.sh [STEP ...]   STEP: env tests core compile imu gdh suite
#                                                (default: all but suite)
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
STEPS=${*:-env tests core compile imu gdh}
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
nproc; $PY -m pytest --version" ;;
    tests) step tests $PY -m pytest tests/test_cuda.py -p no:cacheprovider -W ignore::DeprecationWarning \
             -rA --durations=10 ;;
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
