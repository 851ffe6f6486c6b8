#!/usr/bin/env bash
# The main job end to end on built-in objects, on a fresh machine:
# install -> generate a named split -> validate -> reference and learned predictions -> evaluate -> viewer recording.
set -euo pipefail
cd "$(dirname "$0")/.."
step() {  # run one step and say how long it took (bench/bench_quickstart.py reads these lines)
  local start end
  start=$(date +%s.%N)
  "$@"
  end=$(date +%s.%N)
  echo "quickstart step: $(awk -v a="$start" -v b="$end" 'BEGIN { printf "%.2f", b - a }') s: ${*#.venv/bin/}"
}
step bash scripts/setup.sh
B=.venv/bin/dsr-bench
SPLIT=procedural-novel-mini
DATA=data/$SPLIT
OUT=out/quickstart
mkdir -p "$OUT"
step $B generate --split "$SPLIT" --out "$DATA" --workers 2
step $B validate "$DATA"
step $B info "$DATA"
for model in oracle static dsr; do  # dsr: the CPU track's DSR-Net, whose weights ship with dsr-bench
  step $B predict --model $model --data "$DATA" --split "$SPLIT" --out "$OUT/predictions-$model"
  step $B evaluate "$OUT/predictions-$model" --data "$DATA" --split "$SPLIT" --out "$OUT/results-$model.json"
done
step $B view seq_0000 --data "$DATA" --predictions "$OUT/predictions-static" --save "$OUT/seq_0000.rrd"
echo "done: data in $DATA, results in $OUT (open $OUT/seq_0000.rrd with: .venv/bin/rerun $OUT/seq_0000.rrd)"
