#!/usr/bin/env python3
"""Measures how close udapose's Rust corruptions are to the reference `imagecorruptions-imaug` 1.1.5.

    python lab/scripts/corruption_parity.py                      # all 19 x 5, writes reports/corruptions.{md,json}
    python lab/scripts/corruption_parity.py --only gaussian_noise,zoom_blur --allow-missing
    python lab/scripts/corruption_parity.py --bin path/to/udapose-lab --images 2 --reps 4   # quick look

Run it with the project venv's python (`$HOME/.cache/udapose/venv/bin/python`); it pip-installs the
pinned reference into that interpreter if missing. Both sides corrupt the same test images: by
default 4 crops of 128x320 cut at fixed places from the TORCS background photographs (Debian
package torcs-data). Every (corruption, severity) is one row:

- deterministic corruptions: PSNR between reference and Rust output (worst image), bound >= 30 dB;
- random ones: statistics of the corruption pooled over all images and several seeds per image
  on each side (STATISTICS, REPS), bound: relative deviation <= 10 %.

Rows whose Rust function is still `unimplemented!` are "missing". Exits 1 if any row fails (missing
rows count as failures unless --allow-missing).
"""

import argparse
import datetime
import importlib.metadata
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

REFERENCE = ("imagecorruptions-imaug", "1.1.5")
REPO = Path(__file__).resolve().parents[2]
TORCS_TRACKS = Path("/usr/share/games/torcs/tracks")
CROP = (128, 320)  # height, width: udapose's small car crop

NAMES = [
    "gaussian_noise", "shot_noise", "impulse_noise", "defocus_blur", "glass_blur", "motion_blur",
    "zoom_blur", "snow", "frost", "fog", "brightness", "contrast", "elastic_transform", "pixelate",
    "jpeg_compression", "speckle_noise", "gaussian_blur", "spatter", "saturate",
]
# The reference draws nothing for these: compare pixels.
DETERMINISTIC = {
    "defocus_blur", "zoom_blur", "gaussian_blur", "brightness", "contrast", "saturate", "pixelate",
    "jpeg_compression",
}
# Reference functions that take their own `seed` instead of using np.random's global state.
OWN_SEED = {"impulse_noise", "glass_blur"}
PSNR_BOUND = 30.0
REL_BOUND = 0.10
# Relative deviations divide by max(|reference|, FLOOR) so a statistic near 0 (e.g. the mean
# residual of a geometric warp) is compared in absolute grey levels instead.
FLOOR = {"mean": 1.0, "mean_abs": 1.0, "std": 1.0, "changed": 0.01}


def residual(out, inp):
    return out.astype(np.float64) - inp.astype(np.float64)


# What characterises each random corruption, computed over (output, input) pairs pooled across
# images and seeds, residual = output - input in grey levels (0-255).
STAT_FUNCS = {
    "std": lambda pairs: float(np.concatenate([residual(o, i).ravel() for o, i in pairs]).std()),
    "mean": lambda pairs: float(np.concatenate([residual(o, i).ravel() for o, i in pairs]).mean()),
    "mean_abs": lambda pairs: float(np.concatenate([np.abs(residual(o, i)).ravel() for o, i in pairs]).mean()),
    "changed": lambda pairs: float(np.concatenate([(o != i).ravel() for o, i in pairs]).mean()),
}
STATISTICS = {
    "gaussian_noise": ["std"],
    "shot_noise": ["std"],
    "speckle_noise": ["std"],
    "impulse_noise": ["changed", "std"],
    "glass_blur": ["mean_abs"],
    "motion_blur": ["mean_abs"],
    "snow": ["mean", "std"],
    "frost": ["mean", "std"],
    "fog": ["mean", "std"],
    "spatter": ["mean", "std"],
    "elastic_transform": ["mean_abs", "std"],
}
# Seeds per image for each random corruption. One draw's statistic varies with the draw (motion
# blur's angle, fog's plasma map, frost's image and crop): measured on the reference, its
# coefficient of variation is ~0.19 for motion_blur, ~0.5 for frost's mean, ~0.85 for fog's mean,
# ~0.26 for spatter at severity 1, and below 0.05 for the rest. With n draws per side the relative
# difference of the two pooled means has sd ~ cv * sqrt(2 / n); these keep it near 2.5 % (a 10 %
# bound is then ~4 sd away). Noise corruptions draw per sample, so one image is already thousands
# of draws.
REPS = {
    "gaussian_noise": 2, "shot_noise": 2, "impulse_noise": 2, "speckle_noise": 2, "glass_blur": 2,
    "motion_blur": 32, "snow": 8, "frost": 200, "fog": 600, "spatter": 64, "elastic_transform": 8,
}
STAT_WORDS = {
    "std": "std of residual",
    "mean": "mean of residual",
    "mean_abs": "mean |residual|",
    "changed": "fraction of changed samples",
}


def ensure_reference():
    name, version = REFERENCE
    try:
        installed = importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        installed = None
    if installed != version:
        print(f"installing {name}=={version} into {sys.executable}", file=sys.stderr)
        subprocess.run([sys.executable, "-m", "pip", "install", f"{name}=={version}"], check=True)
    import imagecorruptions

    return imagecorruptions


def torcs_crops(count):
    """`count` 128x320 crops from the RGB background panoramas of TORCS road/ and oval/ tracks:
    files sorted by path, evenly spaced picks, crop centred vertically at 1/3 of the width."""
    if not TORCS_TRACKS.is_dir():
        sys.exit(f"error: {TORCS_TRACKS} not found; install the Debian package torcs-data or pass --input")
    files = []
    for path in sorted(TORCS_TRACKS.glob("*/*/background.png")):
        if path.parts[-3] not in ("road", "oval"):
            continue
        with Image.open(path) as im:
            if im.mode == "RGB" and im.height >= CROP[0] and im.width >= 2 * CROP[1]:
                files.append(path)
    if len(files) < count:
        sys.exit(f"error: only {len(files)} usable background photographs under {TORCS_TRACKS}")
    picks = [files[round(k * (len(files) - 1) / max(count - 1, 1))] for k in range(count)]
    crops = []
    for path in picks:
        img = np.asarray(Image.open(path).convert("RGB"))
        top = (img.shape[0] - CROP[0]) // 2
        left = img.shape[1] // 3
        crops.append((str(path), img[top : top + CROP[0], left : left + CROP[1]].copy()))
    return crops


def input_images(paths):
    return [(p, np.asarray(Image.open(p).convert("RGB"))) for p in paths]


def reference_output(ic, img, name, severity, seed):
    np.random.seed(seed)
    kwargs = {"seed": seed} if name in OWN_SEED else {}
    return ic.corrupt(img, corruption_name=name, severity=severity, **kwargs)


class Missing(Exception):
    pass


def rust_outputs(binary, workdir, in_path, name, severity, seeds):
    """One `udapose-lab corrupt --count` call for all seeds (a process start costs ~0.4 s)."""
    pattern = str(Path(workdir) / "out_{seed}.png")
    cmd = [str(binary), "corrupt", "--name", name, "--severity", str(severity), "--seed", str(seeds[0]),
           "--count", str(len(seeds)), "--in", str(in_path), "--out", pattern]
    run = subprocess.run(cmd, capture_output=True, text=True)
    if run.returncode != 0:
        if "not implemented" in run.stderr:
            raise Missing(name)
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{run.stderr}")
    outs = []
    for seed in seeds:
        path = Path(pattern.replace("{seed}", str(seed)))
        outs.append(np.asarray(Image.open(path).convert("RGB")))
        path.unlink()
    return outs


def psnr(a, b):
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return math.inf if mse == 0 else 10 * math.log10(255.0**2 / mse)


def seeds_for(name, severity, image_index, reps):
    # Disjoint ranges per (corruption, severity, image); the two sides use unrelated generators.
    base = (NAMES.index(name) * 8 + severity) * 1_000_000 + image_index * 10_000
    return list(range(base, base + reps))


def compare(ic, binary, workdir, images, name, severity, reps):
    deterministic = name in DETERMINISTIC
    ref_pairs, rust_pairs = [], []
    for k, (in_path, img) in enumerate(images):
        seeds = seeds_for(name, severity, k, 1 if deterministic else reps)
        ours = rust_outputs(binary, workdir, in_path, name, severity, seeds)
        for seed, out in zip(seeds, ours):
            ref = reference_output(ic, img, name, severity, seed)
            if out.shape != ref.shape:
                raise RuntimeError(f"{name} s{severity}: Rust shape {out.shape} != reference {ref.shape}")
            ref_pairs.append((ref, img))
            rust_pairs.append((out, img))
    if deterministic:
        psnrs = [psnr(r, o) for (r, _), (o, _) in zip(ref_pairs, rust_pairs)]
        worst = min(psnrs)
        return {"kind": "deterministic", "statistic": "PSNR dB (worst image)", "figure": worst,
                "bound": f">= {PSNR_BOUND:g} dB", "pass": worst >= PSNR_BOUND,
                "identical_images": sum(math.isinf(p) for p in psnrs), "images": len(images)}
    stats = {}
    for stat in STATISTICS[name]:
        r = STAT_FUNCS[stat](ref_pairs)
        o = STAT_FUNCS[stat](rust_pairs)
        stats[stat] = {"reference": r, "rust": o, "rel": abs(o - r) / max(abs(r), FLOOR[stat])}
    worst = max(s["rel"] for s in stats.values())
    row = {"kind": "random", "statistic": ", ".join(STAT_WORDS[s] for s in stats), "figure": worst,
           "bound": f"<= {REL_BOUND:.0%} rel.", "pass": worst <= REL_BOUND, "stats": stats,
           "draws": len(ref_pairs)}
    if name == "motion_blur":
        img, ours = images[0][1], rust_pairs[0][0]
        row["angle_fit_psnr"], row["angle_fit"] = motion_blur_fit(img, ours, severity)
        row["pass"] = row["pass"] and row["angle_fit_psnr"] >= PSNR_BOUND
    return row


def motion_blur_fit(img, ours, severity):
    """Motion blur is deterministic once its angle is drawn. Try every distinct tap-shift pattern
    that an angle in [-45, 45) produces (0.01 degree grid) through the reference's `_motion_blur`
    and return the best PSNR to the Rust output and its angle: a pixel-level check of everything
    but the random draw."""
    from imagecorruptions.corruptions import _motion_blur

    radius, sigma = [(10, 3), (15, 5), (15, 8), (15, 12), (20, 15)][severity - 1]  # reference's c
    width = 2 * radius + 1
    patterns = {}
    for angle in np.arange(-45, 45, 0.01):
        point = (width * np.sin(np.deg2rad(angle)), width * np.cos(np.deg2rad(angle)))
        hypot = math.hypot(*point)
        key = tuple((math.ceil(i * point[0] / hypot - 0.5), math.ceil(i * point[1] / hypot - 0.5))
                    for i in range(width))
        patterns.setdefault(key, float(angle))
    return max((psnr(np.uint8(np.clip(_motion_blur(img, radius, sigma, a), 0, 255)), ours), a)
               for a in patterns.values())


def git_commit():
    try:
        head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain"], capture_output=True,
                               text=True, check=True).stdout.strip()
        return head + (" + uncommitted changes" if dirty else "")
    except (subprocess.CalledProcessError, FileNotFoundError):
        return "unknown"


def machine():
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{platform.node()} ({cpu}, {os.cpu_count()} CPUs, {platform.system()} {platform.release()})"


def format_figure(row):
    if row.get("missing"):
        return "—"
    if "error" in row:
        return f"error: {row['error']}"
    if row["kind"] == "deterministic":
        return "identical" if math.isinf(row["figure"]) else f"{row['figure']:.2f} dB"
    parts = [f"{STAT_WORDS[k]} {v['reference']:.4g} vs {v['rust']:.4g}" for k, v in row["stats"].items()]
    if "angle_fit_psnr" in row:
        fit = row["angle_fit_psnr"]
        parts.append(f"PSNR at fitted angle {row['angle_fit']:.2f}°: "
                     + ("identical" if math.isinf(fit) else f"{fit:.1f} dB"))
    return f"{row['figure']:.1%} ({'; '.join(parts)})"


def write_reports(out_dir, header, rows):
    out_dir.mkdir(parents=True, exist_ok=True)
    lines = ["# Corruption parity: Rust vs imagecorruptions-imaug 1.1.5", ""]
    lines += [f"- {k}: {v}" for k, v in header.items()]
    lines += [
        "",
        "Figure: deterministic corruptions, PSNR between the two outputs on the worst image ('identical' = "
        "every image pixel-equal); random ones, the largest relative deviation of the listed statistics "
        "(reference vs Rust, residual = output - input in grey levels, pooled over images and seeds; "
        "deviations divide by max(|reference|, 1 grey level), or 0.01 for the changed fraction). "
        "motion_blur also needs PSNR >= 30 dB between the Rust output and the reference at the best-fitting "
        "angle (first image, first seed).",
        "",
        "| corruption | severity | kind | figure | bound | pass |",
        "|---|---:|---|---|---|---|",
    ]
    for row in rows:
        status = "missing" if row.get("missing") else ("yes" if row["pass"] else "**NO**")
        lines.append(f"| {row['corruption']} | {row['severity']} | {row.get('kind', '—')} | {format_figure(row)} "
                     f"| {row.get('bound', '—')} | {status} |")
    (out_dir / "corruptions.md").write_text("\n".join(lines) + "\n")
    # JSON has no infinity: identical outputs (PSNR inf) are written as null.
    json_rows = [{k: None if isinstance(v, float) and math.isinf(v) else v for k, v in r.items()} for r in rows]
    (out_dir / "corruptions.json").write_text(json.dumps({**header, "rows": json_rows}, indent=2) + "\n")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    target = Path(os.environ.get("CARGO_TARGET_DIR", Path.home() / ".cache/udapose/target"))
    parser.add_argument("--bin", type=Path, default=target / "release" / "udapose-lab")
    parser.add_argument("--images", type=int, default=4, help="number of TORCS crops")
    parser.add_argument("--input", nargs="*", help="use these images instead of the TORCS crops")
    parser.add_argument("--reps", type=int, help="seeds per image for every random corruption (default: REPS)")
    parser.add_argument("--only", help="comma-separated corruption names (default: all 19)")
    parser.add_argument("--severities", default="1,2,3,4,5")
    parser.add_argument("--out-dir", type=Path, default=REPO / "reports")
    parser.add_argument("--allow-missing", action="store_true", help="exit 0 when only missing rows fail")
    args = parser.parse_args()

    ic = ensure_reference()
    if not args.bin.is_file():
        sys.exit(f"error: {args.bin} not found; build with `cargo build --release -p udapose-lab` or pass --bin")
    names = args.only.split(",") if args.only else NAMES
    unknown = [n for n in names if n not in NAMES]
    if unknown:
        sys.exit(f"error: unknown corruption(s) {unknown}")
    severities = [int(s) for s in args.severities.split(",")]

    with tempfile.TemporaryDirectory() as workdir:
        sourced = input_images(args.input) if args.input else torcs_crops(args.images)
        sources = [src for src, _ in sourced]
        images = []
        for k, (_, img) in enumerate(sourced):
            # Saved as PNG for the Rust side (lossless, so both sides see the same pixels).
            path = Path(workdir) / f"image{k}.png"
            Image.fromarray(img).save(path)
            images.append((path, img))
        rows = []
        for name in names:
            for severity in severities:
                row = {"corruption": name, "severity": severity}
                try:
                    row.update(compare(ic, args.bin, workdir, images, name, severity, args.reps or REPS.get(name, 1)))
                except Missing:
                    row.update({"missing": True, "pass": False})
                except RuntimeError as err:  # a Rust error or a shape mismatch: a failed row, not a crash
                    row.update({"error": str(err).strip().splitlines()[-1], "pass": False})
                rows.append(row)
                print(f"{name:18s} s{severity}  {format_figure(row)}", file=sys.stderr)

    header = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": machine(),
        "commit": git_commit(),
        "reference": f"{REFERENCE[0]} {importlib.metadata.version(REFERENCE[0])}, numpy {np.__version__}",
        "images": f"{len(images)}, height x width {images[0][1].shape[0]}x{images[0][1].shape[1]}"
        + ("" if args.input else " (rows centred, columns from 1/3 of the width)") + ": " + ", ".join(sources),
        "seeds per image (random corruptions)": str(args.reps) if args.reps else
        ", ".join(f"{k} {v}" for k, v in REPS.items()),
    }
    write_reports(args.out_dir, header, rows)
    failed = [r for r in rows if not r["pass"] and not (args.allow_missing and r.get("missing"))]
    missing = sum(1 for r in rows if r.get("missing"))
    print(f"{len(rows)} rows, {len(failed)} failing, {missing} missing -> {args.out_dir / 'corruptions.md'}",
          file=sys.stderr)
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
