#!/bin/bash
# What the job's target check sees (GateConfig::min_target_fired): for each MODEL, 3DUDA's round-1
# fired ratios on IMAGES (a folder of crops), to the unchanged model (`source_fired_ratio`, what
# the check reads) and after AdaBN (`fired_ratio_before`). IMAGES "not-cars" stands for the 60
# colour fields and stripes of tests/tests/support/jobs.rs::not_cars (same generator, 160x64,
# resized bilinearly to the model's crop). Used for reports/target-check.md.
#   lab/scripts/target_check.sh IMAGES MODEL...
set -euo pipefail
LAB=${LAB:-${CARGO_TARGET_DIR:-$HOME/.cache/udapose/target}/release/udapose-lab}
PY=${PYTHON:-$HOME/.cache/udapose/venv/bin/python}
IMAGES=$1; shift
WORK=$(mktemp -d); trap 'rm -rf "$WORK"' EXIT
for MODEL in "$@"; do
  dir=$IMAGES
  if [ "$IMAGES" = not-cars ]; then
    dir=$WORK/not-cars; rm -rf "$dir"
    "$PY" - "$dir" "$MODEL/manifest.json" <<'PYTHON'
import json, math, os, sys
from PIL import Image
out, manifest = sys.argv[1], sys.argv[2]
h, w = json.load(open(manifest))["crop"]
os.makedirs(out)
M = (1 << 64) - 1
state = 0x9E3779B97F4A7C15
def nxt():  # xorshift64, as not_cars draws it
    global state
    state ^= (state << 13) & M
    state ^= state >> 7
    state ^= (state << 17) & M
    return (state >> 11) / float(1 << 53)
for i in range(60):
    fx, fy, phase = nxt() * 0.3, nxt() * 0.3, nxt() * 6.0
    base = [nxt(), nxt(), nxt()]
    img = Image.new("RGB", (160, 64))
    px = img.load()
    for y in range(64):
        for x in range(160):
            wave = (math.sin(x * fx + y * fy + phase) + 1.0) / 2.0
            px[x, y] = tuple(min(255, int((b * 0.6 + wave * 0.4) * 255.0)) for b in base)
    if (w, h) != (160, 64):
        img = img.resize((w, h), Image.BILINEAR)
    img.save(os.path.join(out, f"{i:03}.png"))
PYTHON
  fi
  rm -rf "$WORK/out"
  line=$("$LAB" adapt --model "$MODEL" --images "$dir" --out "$WORK/out" --max-rounds 1 </dev/null 2>&1 | grep '^round 1: ')
  "$PY" -c "import json,sys; r=json.loads(sys.argv[1][len('round 1: '):]); print('%s\t%s\t%.4f\t%.4f' % (sys.argv[2], sys.argv[3], r['source_fired_ratio'], r['fired_ratio_before']))" "$line" "$MODEL" "$IMAGES"
done
