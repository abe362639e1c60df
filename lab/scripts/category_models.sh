#!/bin/bash
# The source model of each category beside car, by the shipped car model's recipe
# (models/car/README.md): SynCar-OOD standard rendered for the category, an EfficientNet-Lite0
# trunk from ImageNet, 4 epochs; then its evaluation on every domain. Every step is cached in
# $UDAPOSE_CACHE and skipped when done, and training resumes from its last checkpoint, so a rerun
# (another session) goes on where this one stopped. A model is shipped (models/<category>/ and
# reports/source-model-<category>.md) by lab/scripts/ship_category.py, once its evaluation has
# been read.
#   lab/scripts/category_models.sh [CATEGORY ...]      (default: all five)
# Needs `make assets-all lite-weights`.
set -euo pipefail
CACHE=${UDAPOSE_CACHE:-$HOME/.cache/udapose}
LAB=${LAB:-${CARGO_TARGET_DIR:-$CACHE/target}/release/udapose-lab}
WEIGHTS=${WEIGHTS:-$CACHE/weights/efficientnet-lite0-0.1.0.safetensors}
[ -f "$WEIGHTS" ] || { echo "no $WEIGHTS: run make lite-weights" >&2; exit 1; }
categories=("$@")
[ ${#categories[@]} -gt 0 ] || categories=(aeroplane bus chair sofa diningtable)
for c in "${categories[@]}"; do
  data=$CACHE/data/syncar-ood-standard-$c
  model=$CACHE/train/$c-lite0
  echo "== $c: data $data, model $model"
  # Finished samples are skipped: a rerun completes a partial render.
  "$LAB" synth --profile standard --category "$c" --out "$data"
  [ -f "$model/manifest.json" ] || "$LAB" train --data "$data" --arch efficientnet-lite0 \
    --init-backbone "$WEIGHTS" --epochs 4 --out "$model"
  [ -f "$CACHE/train/$c-lite0-eval.json" ] || "$LAB" eval --model "$model" --data "$data" \
    --out "$CACHE/train/$c-lite0-eval.json"
done
