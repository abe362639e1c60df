#!/usr/bin/env python3
"""Can a service tell which adapted model an image needs, from the image alone?

    lab/scripts/route_probe.py DATA DOMAIN [DOMAIN ...] [--fit N] [--out FILE.md]

Issue 19's probe for per-domain experts chosen at inference (reports/continual-variants.md:
one model cannot hold two domains). Each domain stands for an adaptation job: its signature is
fitted, label-free, on the first N images of its `adapt` split (what a job streams), as a
Gaussian over a few cheap image statistics (colour moments, contrast, gradient and
high-frequency energy, dark channel). Each `test` image is routed to the domain whose
signature gives it the highest likelihood. Prints (and writes with --out) the confusion matrix
and the routing accuracy per domain. No model is run: this measures the router only.
"""
import argparse
import sys
from pathlib import Path

import numpy as np
from PIL import Image


def statistics(path):
    """A dozen numbers that move with weather, blur, noise and light."""
    rgb = np.asarray(Image.open(path).convert("RGB"), dtype=np.float64) / 255.0
    gray = rgb @ np.array([0.299, 0.587, 0.114])
    gx, gy = np.diff(gray, axis=1), np.diff(gray, axis=0)
    lap = gray[1:-1, 1:-1] * 4 - gray[:-2, 1:-1] - gray[2:, 1:-1] - gray[1:-1, :-2] - gray[1:-1, 2:]
    # Energy left after a 4x box blur: what blur removes and noise adds.
    h, w = (gray.shape[0] // 4) * 4, (gray.shape[1] // 4) * 4
    low = gray[:h, :w].reshape(h // 4, 4, w // 4, 4).mean(axis=(1, 3)).repeat(4, 0).repeat(4, 1)
    high = gray[:h, :w] - low
    dark = rgb.min(axis=2)
    sat = rgb.max(axis=2) - dark
    values = [
        *rgb.mean(axis=(0, 1)),
        *rgb.std(axis=(0, 1)),
        np.abs(gx).mean(),
        np.abs(gy).mean(),
        np.abs(lap).mean(),
        high.std(),
        low.std(),
        dark.mean(),
        sat.mean(),
    ]
    return np.log(np.asarray(values) + 1e-4)


def images(data, domain, split, limit=None):
    folder = Path(data) / domain / split / "images"
    files = sorted(p for p in folder.rglob("*.png"))
    if not files:
        sys.exit(f"route_probe: no images under {folder}")
    return files[:limit] if limit else files


class Signature:
    """A Gaussian with a shrunk covariance (a few hundred images, a dozen dimensions)."""

    def __init__(self, x, shrink=0.1):
        self.mean = x.mean(axis=0)
        cov = np.cov(x, rowvar=False)
        cov = (1 - shrink) * cov + shrink * np.diag(np.diag(cov))
        self.inv = np.linalg.inv(cov)
        self.logdet = np.linalg.slogdet(cov)[1]

    def log_likelihood(self, x):
        d = x - self.mean
        return -0.5 * (np.einsum("ij,jk,ik->i", d, self.inv, d) + self.logdet)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data")
    parser.add_argument("domains", nargs="+")
    parser.add_argument("--fit", type=int, default=200, help="adapt images per signature")
    parser.add_argument("--out")
    args = parser.parse_args()
    fit = {d: np.stack([statistics(p) for p in images(args.data, d, "adapt", args.fit)]) for d in args.domains}
    signatures = {d: Signature(x) for d, x in fit.items()}
    lines = [
        f"`lab/scripts/route_probe.py {args.data} {' '.join(args.domains)} --fit {args.fit}`",
        "",
        "Rows: the test images' domain; columns: where the router sends them (share of the row).",
        "",
        "| domain | " + " | ".join(args.domains) + " | routed right |",
        "|---|" + "---:|" * (len(args.domains) + 1),
    ]
    for d in args.domains:
        x = np.stack([statistics(p) for p in images(args.data, d, "test")])
        scores = np.stack([signatures[s].log_likelihood(x) for s in args.domains], axis=1)
        routed = np.bincount(scores.argmax(axis=1), minlength=len(args.domains)) / len(x)
        right = routed[args.domains.index(d)]
        lines.append(f"| {d} | " + " | ".join(f"{r:.3f}" for r in routed) + f" | {right:.3f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        Path(args.out).write_text(text)


if __name__ == "__main__":
    main()
