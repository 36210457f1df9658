#!/usr/bin/env bash
# A SocNav1 protocol (CONFIG, default config/eval_socnav1.yaml: the published grid; rows) on a
# CUDA GPU, run from the repository root of a machine with python3, torch and torch-geometric but no
# network and no checkout of the data: the data is expected at .device_data/socnav1.
# Prints the machine, times training batches on the GPU and the CPU, runs the CUDA tests,
# then the evaluation under a time limit. Writes to $OUT (at most 8 files, 2 folders down):
# log.txt, NAME.tar.gz (the whole results folder) and, in NAME/ (default socnav1-rows), the
# records.jsonl, config.yaml, machine.json and (when the run finished) tables.md.
#
# Settings (environment): PROBES (1; 0 skips the timing probe and the CUDA tests); JOBS (12) worker processes sharing the GPU; BACKBONES (gat);
# EXECUTOR (process; ray: every fit a Ray task on a local Ray instance, GPUS_PER_FIT (0.0625:
# sixteen fits share the GPU) of the GPU and one CPU each, JOBS unset: as many as fit);
# DEVICE (cuda; cpu runs the same steps on the CPU, for a dry run or a comparison);
# EVAL_SECONDS (480) limit of the evaluation (not SECONDS: bash's own counter);
# DATA (.device_data/socnav1); RESUME_FROM: a folder with an earlier run's config.yaml and
# records.jsonl (e.g. a returned socnav1-rows/) whose fits are reused (--resume).
# Missing packages (fastjsonschema, pydantic; myfm and scikit-surprise for a config with peers; ray and those of its needs the machine lacks, for
# EXECUTOR=ray) are installed from .whl/*.whl if present. Ray's wheel is about 79 MB.
set -uo pipefail
cd "$(dirname "$0")/.."
: "${OUT:?set OUT to the folder that collects the results}"
EXECUTOR=${EXECUTOR:-process}
DEVICE=${DEVICE:-cuda}
if [ "$EXECUTOR" = ray ]; then
  workers=(--executor ray ${JOBS:+--jobs "$JOBS"})
  [ "$DEVICE" = cpu ] || workers+=(--gpus-per-fit "${GPUS_PER_FIT:-0.0625}")
  export RAY_AUTH_MODE=disabled  # a local instance that nothing else reaches: no token to write
else
  JOBS=${JOBS:-12}
  workers=(--jobs "$JOBS")
fi
BACKBONES=${BACKBONES:-gat}
PROBES=${PROBES:-1}  # 0: straight to the evaluation, without the timing probe and the CUDA tests
CONFIG=${CONFIG:-config/eval_socnav1.yaml}
NAME=${NAME:-socnav1-rows}
EVAL_SECONDS=${EVAL_SECONDS:-480}
DATA=${DATA:-.device_data/socnav1}
RESULTS=$OUT/$NAME
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
export STARS_SOCNAV1_ROOT=$PWD/$DATA
mkdir -p "$OUT"

run() {
echo "== machine $(date -u +%FT%TZ)"
nvidia-smi || echo "(no nvidia-smi)"
needed='import fastjsonschema, pydantic';
grep -q myfm "$CONFIG" && needed="$needed, myfm"; grep -q surprise_svd "$CONFIG" && needed="$needed, surprise"; [ "$EXECUTOR" = ray ] && needed="$needed, ray"
if ! python3 -c "$needed" 2>/dev/null; then
  if compgen -G '.whl/*.whl' >/dev/null; then
    echo "installing .whl/*.whl into /tmp/site"
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
    export PYTHONPATH=$PYTHONPATH:/tmp/site
  fi
fi
[ "$EXECUTOR" = ray ] && { python3 -c 'import ray; print("ray", ray.__version__)' ||
  { echo "error: EXECUTOR=ray needs ray there (pip download ray==2.60.0 into .whl)"; return 2; }; }
python3 - <<'EOF' || { echo "error: a package is missing (see above)"; return 2; }
import platform, torch, torch_geometric, numpy, scipy, yaml, matplotlib, fastjsonschema, pydantic
print(f'python {platform.python_version()}, torch {torch.__version__} (CUDA {torch.version.cuda}), '
      f'torch_geometric {torch_geometric.__version__}, numpy {numpy.__version__}, '
      f'fastjsonschema {fastjsonschema.VERSION}')
print('GPU:', torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'none visible to torch')
EOF
[ -d "$DATA/raw" ] || { echo "error: no SocNav1 at $DATA (expected $DATA/raw)"; return 2; }

tests=0
if [ "$PROBES" != 0 ]; then
  echo "== timing probe: GAT StARS training batches"
  devices=cpu; [ "$DEVICE" = cpu ] || devices=$DEVICE,cpu
  timeout 180 python3 benchmarks/train_step.py --data-root "$DATA" --backbone gat --devices "$devices" --batches 20
  echo "== CUDA tests"
  timeout 300 python3 -m pytest -q -p no:cacheprovider test/model/test_training.py -k cuda
  tests=$?
fi

echo "== evaluation: $CONFIG, $BACKBONES on $DEVICE, ${workers[*]}, limit $EVAL_SECONDS s"
resume=()
if [ -n "${RESUME_FROM:-}" ]; then
  mkdir -p "$RESULTS"
  cp "$RESUME_FROM/config.yaml" "$RESUME_FROM/records.jsonl" "$RESULTS/"
  resume=(--resume)
fi
nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv -l 30 > "$OUT/gpu.csv" 2>/dev/null &
sampler=$!
timeout "$EVAL_SECONDS" python3 -m offline_training.evaluate --config "$CONFIG" --protocol rows \
  --device "$DEVICE" "${workers[@]}" --data-root "$DATA" --out "$RESULTS" --backbones "$BACKBONES" "${resume[@]}"
status=$?
kill "$sampler" 2>/dev/null
echo "== evaluation exit status $status (124: stopped at the limit; records.jsonl keeps the finished fits)"
echo "GPU use while it ran (every 30 s):"; cat "$OUT/gpu.csv"; rm -f "$OUT/gpu.csv"
wc -l "$RESULTS/records.jsonl" 2>/dev/null

# pack everything, then keep only the small files beside the tarball (8 files at most)
tar czf "$OUT/$NAME.tar.gz" -C "$OUT" "$NAME"
find "$RESULTS" -type f ! -name records.jsonl ! -name config.yaml ! -name machine.json ! -name tables.md -delete
ls -la "$OUT" "$RESULTS"
echo "== CUDA tests exit status $tests, evaluation exit status $status"
# stopping at the limit is planned (and rc 124 would read as the whole command timing out)
[ "$tests" -eq 0 ] && { [ "$status" -eq 0 ] || [ "$status" -eq 124 ]; }
}

run 2>&1 | tee "$OUT/log.txt"
exit "${PIPESTATUS[0]}"
