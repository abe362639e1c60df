#!/usr/bin/env python3
"""udapose's input bench beside libjpeg-turbo, on the same files in the same window.

Runs `udapose-bench input` (which writes reports/input.{json,md} and saves its test images),
then times libjpeg-turbo's own reduced-size decode of each JPEG (Pillow's `draft`, which asks
libjpeg-turbo for DCT scaling at 1/r, r the bench's reduction) and writes
reports/input-libjpeg-turbo.{json,md}: what the field's fastest widely used decoder costs
against the same run's backbone pass. Entropy decoding cannot be skipped at any scale, so this
is the floor a sequential decoder reaches on this CPU.

    lab/scripts/libjpeg_turbo_input.py [--bench PATH] [--repeats N]
"""
import argparse
import io
import json
import os
import subprocess
import sys
import tempfile
import time

from PIL import Image, features


def median_ms(f, repeats):
    f()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        f()
        times.append((time.perf_counter() - t) * 1e3)
    times.sort()
    return times[len(times) // 2]


def pillow_decode(data, r):
    image = Image.open(io.BytesIO(data))
    image.draft("RGB", (image.width // r, image.height // r))
    image.load()
    return image


def main():
    target = os.environ.get("CARGO_TARGET_DIR", os.path.expanduser("~/.cache/udapose/target"))
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bench", default=os.path.join(target, "release", "udapose-bench"))
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--out", default="reports/input-libjpeg-turbo.json")
    args = parser.parse_args()
    if not features.check_feature("libjpeg_turbo"):
        sys.exit("this Pillow is not built on libjpeg-turbo")
    with tempfile.TemporaryDirectory() as images:
        subprocess.run([args.bench, "input", "--repeats", str(args.repeats), "--save-images", images,
                        "--out", "reports/input.json"], check=True)
        bench = json.load(open("reports/input.json"))
        rows = []
        for size in bench["sizes"]:
            name, r = size["image"], size["reduction"]
            if not name.endswith("JPG"):
                continue
            w, h = name.split()[0].split("x")
            with open(os.path.join(images, f"{w}x{h}-noise{size['noise']:g}.jpg"), "rb") as f:
                data = f.read()
            ms = median_ms(lambda: pillow_decode(data, r), args.repeats)
            ours = size["reduced"]["decode_ms"]
            rows.append({"image": name, "noise": size["noise"], "jpeg_bytes": len(data), "reduction": r,
                         "libjpeg_turbo_decode_ms": ms, "udapose_decode_ms": ours,
                         "udapose_decode_crop_ms": size["reduced"]["ms"],
                         "libjpeg_turbo_over_backbone": ms / bench["backbone_ms"]})
            print(f"{name} noise {size['noise']}: libjpeg-turbo at 1/{r} {ms:.1f} ms, udapose {ours:.1f} ms",
                  file=sys.stderr)
    report = {"commit": bench["commit"], "machine": bench["machine"], "backbone_ms": bench["backbone_ms"],
              "pillow": Image.__version__, "repeats": args.repeats, "rows": rows}
    write(args.out, json.dumps(report, indent=2) + "\n")
    write(os.path.splitext(args.out)[0] + ".md", markdown(report))


def markdown(r):
    lines = [
        "# JPEG input: udapose's decoder beside libjpeg-turbo",
        "",
        f"`lab/scripts/libjpeg_turbo_input.py` (commit `{r['commit']}`, {r['machine']}): "
        "`udapose-bench input` (reports/input.md) and, on the same files right after it, libjpeg-turbo's "
        f"reduced-size decode through Pillow {r['pillow']} (`draft`: DCT scaling at 1/r, r the bench's "
        f"reduction); medians of {r['repeats']} runs. One backbone pass in this run: "
        f"**{r['backbone_ms']:.1f} ms**.",
        "",
        "| image | noise | file | r | libjpeg-turbo decode (ms) | / backbone | udapose decode (ms) | udapose decode + crop (ms) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in r["rows"]:
        lines.append(f"| {row['image']} | {row['noise']} | {row['jpeg_bytes'] // 1000} KB | {row['reduction']} | "
                     f"{row['libjpeg_turbo_decode_ms']:.1f} | {100 * row['libjpeg_turbo_over_backbone']:.0f}% | "
                     f"{row['udapose_decode_ms']:.1f} | {row['udapose_decode_crop_ms']:.1f} |")
    lines += ["", "Every scale still entropy-decodes every coefficient of the file (a baseline JPEG without "
              "restart markers is one sequential Huffman stream), so libjpeg-turbo's figure is what a "
              "sequential decoder costs on this CPU, before any crop.", ""]
    return "\n".join(lines)


def write(path, text):
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, path)


if __name__ == "__main__":
    main()
