#!/usr/bin/env python3
"""The Markdown table of an adapt_variants.sh run (e.g. issue 18's lr x rounds sweep).

    lab/scripts/sweep_table.py [--base NAME] WORK SPLIT DOMAIN...

Per domain and variant: Acc@pi/6 on SPLIT, the answers it changes against the base variant
(`--base`, default `bn`, BN only; the source where WORK has no such variant; gained,
lost and McNemar's z = (gained - lost) / sqrt(gained + lost), so that a difference of a few
images reads as the noise it is), the EM rounds it ran (and whether the label-free stop rule
ended it), its backbone steps, seconds, and the false-positive share of its fired matches at
its estimated poses (`udapose-lab eval`'s `false_fired_share`: matches the labels call false,
hidden or over a feature cell from the vertex's true cell).
Variants are the WORK/<name>-<domain> folders, in the order of their logs' times.
"""
import json
import math
import os
import sys

RIGHT_DEG = 30.0  # Acc@pi/6: an error below pi/6, as eval counts it


def load(path):
    with open(path) as f:
        return json.load(f)


def right(evaluation, domain):
    return [e < RIGHT_DEG for e in evaluation["domains"][domain]["errors_deg"]]


def mcnemar(base, other):
    gained = sum(1 for b, o in zip(base, other) if o and not b)
    lost = sum(1 for b, o in zip(base, other) if b and not o)
    z = (gained - lost) / math.sqrt(gained + lost) if gained + lost else 0.0
    return gained, lost, z


def table(work, split, domain, base_name="bn"):
    tag = domain.replace("/", "_")
    suffix = f"-{tag}-{split}.json"
    names = [f[: -len(suffix)] for f in os.listdir(work) if f.endswith(suffix) and not f.startswith("source-")]
    names.sort(key=lambda n: os.path.getmtime(os.path.join(work, n + suffix)))
    source = load(os.path.join(work, f"source{suffix}"))
    has_base = base_name in names
    base = right(load(os.path.join(work, f"{base_name}{suffix}")) if has_base else source, domain)
    label = ("BN only" if base_name == "bn" else f"`{base_name}`") if has_base else "source"
    d = source["domains"][domain]
    rows = [
        f"### `{domain}` ({d['n']} `{split}` images)",
        "",
        f"| variant | Acc@π/6 | vs {label}: +/− (z) | rounds | "
        "backbone steps | s | false-positive share |",
        "|---|---:|---:|---:|---:|---:|---:|",
        f"| source | {d['acc_pi_6']:.3f} | | | | | {d.get('false_fired_share', float('nan')):.3f} |",
    ]
    for name in names:
        evaluation = load(os.path.join(work, name + suffix))
        m = evaluation["domains"][domain]
        run = load(os.path.join(work, f"{name}-{tag}", "manifest.json"))["training"]["run"]
        rounds = len(run["rounds"])
        stopped = " (stop rule)" if run.get("converged") else ""
        gained, lost, z = mcnemar(base, right(evaluation, domain))
        rows.append(
            f"| {name} | {m['acc_pi_6']:.3f} | +{gained} −{lost} ({z:+.1f}) | {rounds}{stopped} | "
            f"{run['backbone_steps']} | {run['seconds']:.0f} | {m.get('false_fired_share', float('nan')):.3f} |"
        )
    return "\n".join(rows)


def main():
    args = sys.argv[1:]
    base = "bn"
    if args[:1] == ["--base"] and len(args) > 1:
        base, args = args[1], args[2:]
    if len(args) < 3:
        sys.exit(__doc__)
    work, split, domains = args[0], args[1], args[2:]
    print("\n\n".join(table(work, split, d, base) for d in domains))


if __name__ == "__main__":
    main()
