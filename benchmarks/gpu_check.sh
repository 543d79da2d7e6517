#!/usr/bin/env bash
# The device checks for a lent GPU machine, as one prepared script of about 8 minutes: versions,
# the compile-everything command on an empty cache, frames/s of lrf_net and lrf_net_plus end to
# end at 100k and 1M keypoints (bench_speed.py on the BR dragon, bench_scale.py on a 1M-point
# cloud with search="device"; bench_device_split.py: the search, the frames and the whole call
# timed apart), then the tests that run the jitted and device paths. Each step has
# its own time limit, so a slow one cannot eat the next; every log goes to $OUT.
#
#   LRF_DATA=/path/to/data OUT=out/gpu bash benchmarks/gpu_check.sh
#
# LRF_DATA needs bologna_retrieval/models/dragon; the tests run without it (the data tests skip:
# a lent machine carries only what the benchmarks read). SMALL=1 shrinks every size (a dry run on
# a CPU); SKIP="scale_plus tests" leaves steps out.
set -u
OUT=${OUT:-out/gpu}
PY=${PY:-python3}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
export NUMBA_CACHE_DIR=${NUMBA_CACHE_DIR:-/tmp/gpu_check_numba}  # empty: the compile is timed
if [ "${SMALL:-0}" = 1 ]; then K1=2000; K2=4000; N=50000; T=0.3; else K1=100000; K2=1000000; N=1000000; T=1; fi
step() {  # step NAME SECONDS COMMAND...: runs COMMAND under a limit, logs to $OUT/NAME.log
  local name=$1 limit=$2; shift 2
  case " ${SKIP:-} " in *" $name "*) echo "== $name skipped"; return;; esac
  local lim; lim=$(awk -v a="$limit" -v t="$T" 'BEGIN{print int(a*(t<1?1:t))}')
  echo "== $name (limit ${lim}s) $(date +%T)"
  local t0=$SECONDS
  timeout -k 5 "$lim" "$@" >"$OUT/$name.log" 2>&1
  local rc=$?
  echo "   rc=$rc in $((SECONDS - t0))s"
  if [ "$name" = tests ]; then  # -v names each result as it comes: kept even if the limit hits
    grep -E " (FAILED|ERROR) " "$OUT/$name.log" | sed 's/^/   /'; tail -n 1 "$OUT/$name.log"
  else
    tail -n 25 "$OUT/$name.log" | grep -v '^\s*$' | sed 's/^/   /'
  fi
}
step versions 60 bash -c "nvidia-smi -L; $PY -c 'import sys, jax, numba, numpy, scipy
print(sys.version.split()[0], \"jax\", jax.__version__, jax.devices(), \"numba\", numba.__version__,
      \"numpy\", numpy.__version__, \"scipy\", scipy.__version__)'; nproc"
step import 30 $PY -c "import time; t = time.perf_counter(); import lrf_jax; print(f'import lrf_jax {time.perf_counter() - t:.3f} s')"
step compile 150 $PY -m lrf_jax.cli.compile
step speed 150 $PY benchmarks/bench_speed.py --no-pcl --counts 10000 $K1 $K2 --methods lrf_net lrf_net_plus
step split 120 $PY benchmarks/bench_device_split.py --points $N --keypoints $K2 --chunks 65536 --repeat 1
step scale_plus 90 $PY benchmarks/bench_scale.py --rows cloud --points $N --keypoints $K2 --method lrf_net_plus --search device --chunk-size 65536 --repeat 2
step scale_net 60 $PY benchmarks/bench_scale.py --rows cloud --points $N --keypoints $K2 --method lrf_net --search device --chunk-size 65536 --repeat 2
step tests 150 env -u LRF_DATA XLA_PYTHON_CLIENT_PREALLOCATE=false $PY -m pytest -v -n 16 -p no:cacheprovider -p no:benchmark --timeout 60 tests/test_device_search.py tests/test_lrf_net.py tests/test_method_properties.py tests/test_losses.py tests/test_train_distributed.py tests/test_lrf_net_plus_points_only.py tests/test_descriptors.py tests/test_train.py tests/test__jax_matmul_precision.py
echo "== done $(date +%T)"
