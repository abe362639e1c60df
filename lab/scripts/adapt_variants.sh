#!/bin/bash
# Adapts MODEL on each DOMAIN's `adapt` split with the variants below and evaluates each result on
# the same split and on `test` (Acc@π/6 and image count). Results are cached in WORK, so a rerun
# resumes. Used for reports/adapt-defaults.md's tables.
#   [VARIANTS=FILE] [SPLITS="adapt test"] lab/scripts/adapt_variants.sh DATA MODEL WORK DOMAIN...
# VARIANTS: a file of "name flags..." lines instead of the list below (lab/scripts/sweep-lr-rounds.txt
# is issue 18's lr x rounds sweep); SPLITS: the splits each result is evaluated on.
# e.g. lab/scripts/adapt_variants.sh ~/.cache/udapose/run/syncar-quick ~/.cache/udapose/run/quick-model /tmp/variants combined occ-l1 corrupt/fog
set -euo pipefail
LAB=${LAB:-${CARGO_TARGET_DIR:-$HOME/.cache/udapose/target}/release/udapose-lab}
DATA=$1; MODEL=$2; WORK=$3; shift 3
mkdir -p "$WORK"
acc() { python3 -c "import json;m=json.load(open('$1'))['domains']['$2'];print('%.3f'%m['acc_pi_6'], m['n'])"; }
evaluate() { # model domain split out
  [ -f "$4" ] || "$LAB" eval --model "$1" --data "$DATA" --split "$3" --domains "$2" --out "$4" </dev/null >/dev/null 2>&1
}
SPLITS=${SPLITS:-adapt test}
variants() {
  if [ -n "${VARIANTS:-}" ]; then grep -v '^#' "$VARIANTS"; return; fi
  cat <<'LIST'
bn --max-rounds 1 --no-backbone --alpha 1
default
fired --positives fired
object --positives object
best --vertex-matches best
lr1e-4 --lr 1e-4
lr1e-4-r10 --lr 1e-4 --max-rounds 10
LIST
}
for D in "$@"; do
  tag=${D//\//_}
  for split in $SPLITS; do
    evaluate "$MODEL" "$D" $split "$WORK/source-$tag-$split.json"
    echo "$D source $split $(acc "$WORK/source-$tag-$split.json" "$D")"
  done
  while read -r name flags; do
    out=$WORK/$name-$tag
    if [ ! -d "$out" ]; then
      start=$(date +%s)
      # shellcheck disable=SC2086 # flags are words
      "$LAB" adapt --model "$MODEL" --images "$DATA/$D/adapt/images/car" --out "$out" $flags </dev/null > "$out.log" 2>&1 \
        || { echo "$D $name failed"; tail -3 "$out.log"; continue; }
      echo "  ($(( $(date +%s) - start )) s)" >> "$out.log"
    fi
    line="$D $name"
    for split in $SPLITS; do
      evaluate "$out" "$D" $split "$out-$split.json"
      line="$line $split $(acc "$out-$split.json" "$D")"
    done
    echo "$line $(tail -1 "$out.log")"
  done < <(variants)
done
