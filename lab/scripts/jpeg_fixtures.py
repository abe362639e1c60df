"""Writes service/testdata/*.jpg: small JPEGs with restart markers, chroma subsamplings and a
progressive scan, for the DC-only decoder's tests (image's encoder writes none of these).

    python lab/scripts/jpeg_fixtures.py   # venv python (Pillow)
"""
import math
from pathlib import Path

from PIL import Image

OUT = Path(__file__).resolve().parents[2] / "service" / "testdata"
W, H = 203, 141


def pattern(mode):
    im = Image.new(mode, (W, H))
    px = im.load()
    for y in range(H):
        for x in range(W):
            rgb = tuple(int(128 + 100 * math.sin(x / 17 + c) * math.cos(y / 11)) for c in range(3))
            px[x, y] = rgb if mode == "RGB" else rgb[0]
    return im


FIXTURES = {
    "restart-420.jpg": ("RGB", dict(subsampling=2, restart_marker_blocks=7)),
    "restart-422.jpg": ("RGB", dict(subsampling=1, restart_marker_blocks=3)),
    "restart-444.jpg": ("RGB", dict(subsampling=0, restart_marker_rows=1)),
    "restart-grey.jpg": ("L", dict(restart_marker_blocks=5)),
    "progressive.jpg": ("RGB", dict(progressive=True)),
}

if __name__ == "__main__":
    OUT.mkdir(parents=True, exist_ok=True)
    for name, (mode, options) in FIXTURES.items():
        pattern(mode).save(OUT / name, "JPEG", quality=90, **options)
        print(OUT / name)
