#!/bin/bash
# The 3DUDA report of each shipped category beside car (the categories issue: combined, occ-l1
# and the five corruptions of BENCHMARK.md §5, each with the same-budget and the strong oracle):
# `udapose-lab report --profile standard --category C` on models/C and the category's dataset in
# $UDAPOSE_CACHE (lab/scripts/category_models.sh renders it). Every stage is cached in
# $UDAPOSE_CACHE/run/report-standard-C and skipped when done, so a rerun (another session) goes
# on where this one stopped. The report goes to reports/syncar-ood-C.{json,md} and its PNGs.
# The global-filter ablation stays car's alone (`--ablation none`): it answers a question about
# the method, not about the category; so does adaptation over seeds (`--seeds 1`). About 2-6
# hours per category on the 2-core CPU, most of it the strong oracle (10-40 passes over 300
# images). Run one report at a time: two libtorch jobs on 2 cores slow each other several-fold
# (a strong-oracle pass went from ~25 s to ~230 s beside two others).
#   lab/scripts/category_reports.sh [CATEGORY ...]     (default: every shipped one but car)
set -euo pipefail
CACHE=${UDAPOSE_CACHE:-$HOME/.cache/udapose}
LAB=${LAB:-${CARGO_TARGET_DIR:-$CACHE/target}/release/udapose-lab}
DOMAINS=combined,occ-l1,corrupt/gaussian_noise,corrupt/glass_blur,corrupt/fog,corrupt/contrast,corrupt/speckle_noise
categories=("$@")
if [ ${#categories[@]} -eq 0 ]; then
  for manifest in models/*/manifest.json; do
    c=$(basename "$(dirname "$manifest")")
    [ "$c" = car ] || categories+=("$c")
  done
fi
# The report runs its binary once per stage, for hours: it runs a copy, so that a rebuild
# meanwhile (`make build`) neither breaks it nor mixes two builds in one report.
mkdir -p "$CACHE/run"
pinned=$(mktemp "$CACHE/run/udapose-lab.XXXXXX")
trap 'rm -f "$pinned"' EXIT
install -m 755 "$LAB" "$pinned"
for c in "${categories[@]}"; do
  [ -f "models/$c/manifest.json" ] || { echo "no models/$c: ship it first (lab/scripts/ship_category.py $c)" >&2; exit 1; }
  echo "== $c"
  "$pinned" report --profile standard --category "$c" --data "$CACHE/data/syncar-ood-standard-$c" \
    --work "$CACHE/run/report-standard-$c" --domains "$DOMAINS" --ablation none --seeds 1
done
