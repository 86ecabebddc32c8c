#!/usr/bin/env bash
# The many-core measurements (and the CUDA checks) in one call on a
# machine with 16 cores and a GPU, whose Python has numba, scikit-image
# and numba-cuda but reaches no package registry.
#
#   bash bench/device.sh fetch   # here, with pip: the wheels it needs, into .whl/ (ignored)
#   bash bench/device.sh cpu     # there, with .whl carried: the thread-scaling benchmarks
#                                # (timeout_s 600; carry [".whl"]; OUT is the tool's folder)
#   bash bench/device.sh gpu     # there: tests/test_cuda.py on the GPU and bench.gpu
#
# What it carries: numpy 2.4 (numba-cuda 0.30.4 does not import with numpy
# 2.5) and TBB, the threading layer the package prefers (without it Numba
# falls back to OpenMP there, which scales worse). pip
# --target leaves a wheel's shared libraries out, so TBB's are unpacked
# beside the packages and put on the loader's path.
#
# Every step has its own time limit (LIMIT_<STEP> seconds; a step that runs
# over is cut and the rest goes on). The limits of `cpu` add up to 555 s, so
# it fits one 10-minute call (timeout_s 600) with the set-up; `gpu`'s to 390 s.
# THREADS (default 1,2,4,8,16), RAYS (default 1000000) and REPEATS size it.
# The log and every record written come back in $OUT (bench-results.tgz
# holds bench/results/ files the run wrote); without $OUT they stay in
# bench/results/ and device-log.txt.
set -uo pipefail
cd "$(dirname "$0")/.."

WHEELS=.whl
SITE=${SITE:-/tmp/logsph-site}
THREADS=${THREADS:-1,2,4,8,16}
RAYS=${RAYS:-1000000}
REPEATS=${REPEATS:-5}
export PYTHON=${PYTHON:-python3}

fetch() {
    mkdir -p "$WHEELS"
    "$PYTHON" -m pip download --no-deps --only-binary=:all: --python-version 3.12 \
        --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
        --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d "$WHEELS" \
        numpy==2.4.6 tbb==2023.2.0 tcmlib==1.6.0
    du -sh "$WHEELS"
}

setup() {
    if compgen -G "$WHEELS/*.whl" >/dev/null; then
        "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
            --target "$SITE" "$WHEELS"/*.whl || return 1
        "$PYTHON" - "$SITE/lib" "$WHEELS"/*.whl <<'LIBS' || return 1
import os, shutil, sys, zipfile
os.makedirs(sys.argv[1], exist_ok=True)
for wheel in sys.argv[2:]:  # the shared libraries a wheel installs into <prefix>/lib
    with zipfile.ZipFile(wheel) as archive:
        for name in archive.namelist():
            if ".data/data/lib/" in name and not name.endswith("/"):
                with archive.open(name) as part, \
                        open(os.path.join(sys.argv[1], os.path.basename(name)), "wb") as copy:
                    shutil.copyfileobj(part, copy)
LIBS
        export PYTHONPATH="$SITE:$PWD" LD_LIBRARY_PATH="$SITE/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
    else
        echo "no wheels in $WHEELS: the machine's own numpy and threading layer" \
             "(bash bench/device.sh fetch, here, then carry .whl)"
        export PYTHONPATH="$PWD"
    fi
    export PYTHONUNBUFFERED=1
    "$PYTHON" - <<'EOF'
import os, platform, numba, numpy
print("Python", platform.python_version(), "numpy", numpy.__version__, "numba", numba.__version__,
      "cores", os.cpu_count(), "Numba threads", numba.config.NUMBA_NUM_THREADS)
import logsph_trace  # applies the package's preference for TBB
from numba import njit, prange
@njit(parallel=True)
def touch(a):
    for i in prange(a.shape[0]):
        a[i] = i
touch(numpy.zeros(64))
print("threading layer", numba.threading_layer())
EOF
    lscpu | grep -E 'Model name|^CPU\(s\)|Thread|Socket|NUMA node\(s\)|L3' || true
    cat /sys/kernel/mm/transparent_hugepage/enabled 2>/dev/null || true
    git rev-parse --short HEAD 2>/dev/null || true
}

# step NAME LIMIT COMMAND...: run a step under its time limit; report how it ended.
step() {
    local name=$1 limit=$2
    shift 2
    echo
    echo "=== $name (limit ${limit} s): $*"
    local start=$SECONDS
    timeout --kill-after=10 "$limit" "$@"
    local status=$?
    echo "=== $name: exit $status after $((SECONDS - start)) s"
}

# Numba compiles every kernel on first use, and no cache travels (it is keyed
# to the processor). One pass of each benchmark at the smallest sizes, the four
# at once on the many cores, compiles them, so that the measured steps time no
# compilation; the records they write are overwritten, and `cpu` returns only
# the records written after them.
compile() {
    local logs pids=() failed=0
    logs=$(mktemp -d)
    "$PYTHON" -m bench.run --rays 2000 --threads 1,2 --repeats 1 --no-first-call \
        --out "$logs/traversal.json" >"$logs/run.log" 2>&1 & pids+=($!)
    "$PYTHON" -m bench.occupancy --threads 1,2 --repeats 1 >"$logs/occupancy.log" 2>&1 & pids+=($!)
    "$PYTHON" -m bench.cone --threads 1,2 --repeats 1 >"$logs/cone.log" 2>&1 & pids+=($!)
    "$PYTHON" -m bench.faults --rays 2000 --threads 1,2 --repeats 1 >"$logs/faults.log" 2>&1 &
    pids+=($!)
    for pid in "${pids[@]}"; do wait "$pid" || failed=1; done
    [ "$failed" = 0 ] || tail -n 5 "$logs"/*.log
    return "$failed"
}

cpu() {
    step compile "${LIMIT_COMPILE:-200}" bash bench/device.sh compile
    touch "$STAMP"
    step traversal "${LIMIT_TRAVERSAL:-110}" "$PYTHON" -m bench.run --rays "$RAYS" \
        --threads "$THREADS" --repeats "$REPEATS" --no-first-call
    step occupancy "${LIMIT_OCCUPANCY:-80}" "$PYTHON" -m bench.occupancy --threads "$THREADS"
    step integrate_kernels "${LIMIT_KERNELS:-45}" "$PYTHON" -m bench.integrate_kernels \
        --threads "$THREADS"
    step cone "${LIMIT_CONE:-30}" "$PYTHON" -m bench.cone --threads "$THREADS"
    step faults "${LIMIT_FAULTS:-90}" "$PYTHON" -m bench.faults --rays "$RAYS" \
        --threads "$THREADS" --repeats "$REPEATS"
}

gpu() {
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv || true
    step test_cuda "${LIMIT_TEST_CUDA:-240}" "$PYTHON" -m pytest -q -p no:cacheprovider \
        tests/test_cuda.py
    step gpu_bench "${LIMIT_GPU_BENCH:-150}" "$PYTHON" -m bench.gpu
}

collect() {
    local out=${OUT:-}
    [ -n "$out" ] || return 0
    find bench/results -type f -newer "$STAMP" -print0 \
        | tar --null -czf "$out/bench-results.tgz" -T - 2>/dev/null
    tar -tzf "$out/bench-results.tgz" 2>/dev/null | sed 's/^/returned: /'
}

mode=${1:-}
case "$mode" in
    fetch) fetch ;;
    compile) compile ;;  # run by `cpu`, after `setup`
    cpu | gpu)
        STAMP=$(mktemp)
        LOG=${OUT:+$OUT/}device-log.txt
        trap collect EXIT
        { setup && "$mode"; } 2>&1 | tee "$LOG"
        ;;
    *)
        echo "usage: bash bench/device.sh fetch | cpu | gpu" >&2
        exit 2
        ;;
esac
