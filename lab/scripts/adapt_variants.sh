#!/bin/bash
# Adapts MODEL on each DOMAIN's `adapt` split with the variants below and evaluates each result on
# the same split and on `test` (Acc@π/6 and image count). Results are cached in WORK, so a rerun
# resumes. Used for reports/adapt-defaults.md's tables.
#   [VARIANTS=FILE] [SPLITS="adapt test"] lab/scripts/adapt_variants.sh DATA MODEL WORK DOMAIN...
# VARIANTS: a file of "name flags..." lines instead of the list below (lab/scripts/sweep-lr-rounds.txt
# is issue 18's lr x rounds sweep); SPLITS: the splits each result is evaluated on.
# HOLD=N: adapt on all but the last N images of the adapt split and evaluate on those N instead
# (split `held`, linked under WORK/data): accuracy on images the adaptation never saw, as the
# service's jobs are judged and as `test` measures, but without touching `test`. On the adapt
# split itself a run is scored on the images it trained on (transductive).
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
# held_out DOMAIN: links WORK/data/DOMAIN/{fit,held} to the first and last HOLD adapt images.
held_out() {
  local src=$ORIG/$1/adapt dst=$WORK/data/$1 n
  n=$(wc -l < "$src/lists/car/list.txt")
  [ "$HOLD" -lt "$n" ] || { echo "HOLD=$HOLD leaves no image of $1 to adapt on" >&2; exit 1; }
  [ -f "$dst/held/lists/car/list.txt" ] && return
  for part in fit held; do
    mkdir -p "$dst/$part/images/car" "$dst/$part/annotations/car" "$dst/$part/lists/car"
    if [ $part = fit ]; then head -n $((n - HOLD)) "$src/lists/car/list.txt"; else tail -n "$HOLD" "$src/lists/car/list.txt"; fi \
      > "$dst/$part/lists/car/list.tmp"
    while read -r f; do
      ln -sf "$src/images/car/$f" "$dst/$part/images/car/$f"
      ln -sf "$src/annotations/car/${f%.*}.npz" "$dst/$part/annotations/car/${f%.*}.npz"
    done < "$dst/$part/lists/car/list.tmp"
    mv "$dst/$part/lists/car/list.tmp" "$dst/$part/lists/car/list.txt"
  done
}
if [ -n "${HOLD:-}" ]; then
  SPLITS=held
  ORIG=$DATA DATA=$WORK/data
  mkdir -p "$DATA"
  cp -n "$ORIG/manifest.json" "$DATA/"
fi
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
  images=$DATA/$D/adapt/images/car
  if [ -n "${HOLD:-}" ]; then held_out "$D"; images=$DATA/$D/fit/images/car; fi
  for split in $SPLITS; do
    evaluate "$MODEL" "$D" $split "$WORK/source-$tag-$split.json"
    echo "$D source $split $(acc "$WORK/source-$tag-$split.json" "$D")"
  done
  while read -r name flags; do
    out=$WORK/$name-$tag
    if [ ! -d "$out" ]; then
      start=$(date +%s)
      # shellcheck disable=SC2086 # flags are words
      "$LAB" adapt --model "$MODEL" --images "$images" --out "$out" $flags </dev/null > "$out.log" 2>&1 \
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
