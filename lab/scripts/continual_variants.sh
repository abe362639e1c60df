#!/bin/bash
# Can one adapted model keep an earlier domain's gain while it adapts to a new one? Two steps on
# the quick set: MODEL adapted to fog, then that model adapted to clear (source) images, (a)
# alone, (b) with K fog images replayed among the 60 clear ones, (c) as a weight-space blend of
# the fog and the clear models (every float tensor, BatchNorm statistics included). Each result is
# scored on the adapt splits of both domains (labels only to score; never tune on test) and, for
# information, on test. Results are cached in WORK, so a rerun resumes. Used for
# reports/continual-quick.md.
#   lab/scripts/continual_variants.sh DATA MODEL WORK
set -euo pipefail
LAB=${LAB:-${CARGO_TARGET_DIR:-$HOME/.cache/udapose/target}/release/udapose-lab}
PY=${PY:-$HOME/.cache/udapose/venv/bin/python}
HERE=$(cd "$(dirname "$0")" && pwd)
DATA=$1; MODEL=$2; WORK=$3
FOG=$DATA/corrupt/fog/adapt/images/car CLEAR=$DATA/source/adapt/images/car
mkdir -p "$WORK" && cd "$WORK"
adapt() { [ -d "$2" ] || "$LAB" adapt --model "$1" --images "$3" --out "$2" > "$2.log" 2>&1; }
adapt "$MODEL" m-fog "$FOG"
adapt m-fog m-clear "$CLEAR"
for k in 8 16 32 60; do
  if [ ! -d mix-$k ]; then
    rm -rf mix-$k.tmp && mkdir -p mix-$k.tmp && cp "$CLEAR"/*.png mix-$k.tmp/
    mapfile -t fog < <(find "$FOG" -name '*.png' | sort)
    for f in "${fog[@]:0:$k}"; do cp "$f" "mix-$k.tmp/fog-$(basename "$f")"; done
    mv mix-$k.tmp mix-$k
  fi
  adapt m-fog m-mix-$k mix-$k
done
for lam in 0.25 0.5 0.75; do [ -d m-blend-$lam ] || "$PY" "$HERE/blend_models.py" m-fog m-clear $lam m-blend-$lam; done
printf '| model | fog adapt | clear adapt | fog test | clear test |\n|---|---:|---:|---:|---:|\n'
for m in "$MODEL" m-fog m-clear m-mix-8 m-mix-16 m-mix-32 m-mix-60 m-blend-0.25 m-blend-0.5 m-blend-0.75; do
  n=$(basename "$m"); row="| $n"
  for split in adapt test; do
    [ -f "eval-$n-$split.json" ] || "$LAB" eval --model "$m" --data "$DATA" --split $split --domains source,corrupt/fog --out "eval-$n-$split.json" > /dev/null 2>&1
  done
  row="$row $(python3 -c "
import json
a, t = (json.load(open('eval-$n-%s.json' % s))['domains'] for s in ('adapt', 'test'))
print(' '.join('| %.3f' % d[k]['acc_pi_6'] for d in (a, t) for k in ('corrupt/fog', 'source')))")"
  echo "$row |"
done
