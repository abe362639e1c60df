#!/usr/bin/env python3
"""PyTorch side of the backbone parity test (engine/tests/backbone.rs runs it; METHOD.md §4).

    python lab/scripts/backbone_parity.py --out /tmp/parity [--arch resnet18 --arch resnet50] [--seed 0]

For each architecture it writes into OUT/<arch>/:

- weights.safetensors: a randomly initialised torchvision ResNet (`weights=None`, seeded; nothing
  is downloaded) whose BatchNorm affine parameters are randomised and whose running statistics are
  estimated on a random calibration batch (at init they are 1/0/0/1, which would hide a swapped
  mean/var or a misplaced BN, and activations grow to ~1e3), exported through
  export_torchvision.py's command line from a saved state dict. resnet18 keeps the int64
  `num_batches_tracked` counters, the other archs drop them, so the Rust loader sees both forms;
- decoder.safetensors: the "resnetext" decoder of METHOD.md §4 (DoubleConv on layer4, Up with
  layer3, Up with layer2, 1x1 conv to D without bias) written here from the spec, under the names
  udapose uses (upsample0.doubleconv.{0,1,3,4}.*, upsample{1,2}.doubleconv.doubleconv.*,
  out_layer.weight), randomly initialised, BatchNorm treated as above;
- input.safetensors: `image`, a random u8 H x W x 3 RGB image, and `input`, the 1 x 3 x H x W
  tensor torchvision-style preprocessing makes of it (x / 255 - ImageNet mean) / std;
- reference.safetensors: `layer2`, `layer3`, `layer4` (the trunk's taps) and `features` (the
  decoder's L2-normalised N x D x H/8 x W/8 output), all computed in eval mode.

Exit status 3 with a message naming `make test` when torch, torchvision or safetensors is missing.
"""

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

MEAN = (0.485, 0.456, 0.406)
STD = (0.229, 0.224, 0.225)
# (layer2, layer3, layer4) widths and decoder widths per METHOD.md §4:
# (DoubleConv on layer4 out, Up1 (in, mid, out), Up2 (in, mid, out)).
WIDTHS = {
    "resnet18": ((128, 256, 512), 256, (512, 256, 128), (256, 128, 64)),
    "resnet34": ((128, 256, 512), 256, (512, 256, 128), (256, 128, 64)),
    "resnet50": ((512, 1024, 2048), 1024, (2048, 1024, 512), (1024, 512, 256)),
}


def need_modules():
    try:
        import safetensors  # noqa: F401
        import torch  # noqa: F401
        import torchvision  # noqa: F401
    except ImportError as e:
        print(
            f"backbone_parity.py: {e} (interpreter {sys.executable}). The parity test needs torch==2.13.0, "
            "torchvision==0.28.0 and safetensors in this interpreter: run `make test` (it installs them into "
            "the project venv), or point UDAPOSE_PYTHON at a python that has them.",
            file=sys.stderr,
        )
        sys.exit(3)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--arch", action="append", choices=sorted(WIDTHS), help="repeatable; default resnet18 and resnet50")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--height", type=int, default=64)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--dim", type=int, default=128)
    args = ap.parse_args(argv)
    need_modules()

    import torch
    import torch.nn as nn
    import torch.nn.functional as F
    from safetensors.torch import save_file

    import export_torchvision

    class DoubleConv(nn.Module):
        """(3x3 conv pad 1 with bias, BN, ReLU) x 2 through `mid` channels."""

        def __init__(self, cin, cout, mid):
            super().__init__()
            self.doubleconv = nn.Sequential(
                nn.Conv2d(cin, mid, 3, padding=1),
                nn.BatchNorm2d(mid),
                nn.ReLU(),
                nn.Conv2d(mid, cout, 3, padding=1),
                nn.BatchNorm2d(cout),
                nn.ReLU(),
            )

        def forward(self, x):
            return self.doubleconv(x)

    class Up(nn.Module):
        """Bilinear x2 (align_corners), concatenate [tap, upsampled], DoubleConv(cin, cout, mid)."""

        def __init__(self, cin, mid, cout):
            super().__init__()
            self.up = nn.Upsample(scale_factor=2, mode="bilinear", align_corners=True)
            self.doubleconv = DoubleConv(cin, cout, mid)

        def forward(self, x, tap):
            x = self.up(x)
            assert x.shape[2:] == tap.shape[2:], (x.shape, tap.shape)
            return self.doubleconv(torch.cat([tap, x], dim=1))

    class Decoder(nn.Module):
        def __init__(self, arch, dim):
            super().__init__()
            (_, _, c4), d0, up1, up2 = WIDTHS[arch]
            self.upsample0 = DoubleConv(c4, d0, d0)
            self.upsample1 = Up(*up1)
            self.upsample2 = Up(*up2)
            self.out_layer = nn.Conv2d(up2[2], dim, 1, bias=False)

        def forward(self, l2, l3, l4):
            x = self.upsample2(self.upsample1(self.upsample0(l4), l3), l2)
            return F.normalize(self.out_layer(x), p=2, dim=1)

    def randomise_bn(module, gen, calibration):
        """Random BN affine parameters, then running statistics estimated on `calibration` (train-mode
        forward, cumulative average): per-channel values that are neither 0 nor 1 and activations of
        order 1 through the whole network, as with trained weights (at torchvision's init layer4 of a
        ResNet-50 reaches ~1e3, where float32 rounding alone exceeds the 1e-4 tolerance)."""
        bns = [m for m in module.modules() if isinstance(m, nn.BatchNorm2d)]
        with torch.no_grad():
            for m in bns:
                n = m.num_features
                m.weight.copy_(0.5 + torch.rand(n, generator=gen))
                m.bias.copy_(0.2 * torch.randn(n, generator=gen))
                m.reset_running_stats()
                m.momentum = None
            module.train()
            calibration()
            module.eval()
            for m in bns:
                m.momentum = 0.1
                m.num_batches_tracked.fill_(int(torch.randint(1, 1000, (1,), generator=gen)))

    def trunk(net, x):
        x = net.maxpool(net.relu(net.bn1(net.conv1(x))))
        l2 = net.layer2(net.layer1(x))
        l3 = net.layer3(l2)
        return l2, l3, net.layer4(l3)

    for arch in args.arch or ["resnet18", "resnet50"]:
        out = args.out / arch
        out.mkdir(parents=True, exist_ok=True)
        gen = torch.Generator().manual_seed(args.seed)

        net = export_torchvision.build(arch, args.seed)
        calib = torch.randn(4, 3, args.height, args.width, generator=gen)
        randomise_bn(net, gen, lambda: net(calib))
        pth = out / "model.pth"
        torch.save(net.state_dict(), pth)
        cli = ["--arch", arch, "--state-dict", str(pth), "--out", str(out / "weights.safetensors")]
        if arch != "resnet18":
            cli.append("--drop-num-batches-tracked")
        export_torchvision.main(cli)
        pth.unlink()

        torch.manual_seed(args.seed + 1)
        dec = Decoder(arch, args.dim)
        with torch.no_grad():
            taps = trunk(net, calib)
        randomise_bn(dec, gen, lambda: dec(*taps))
        save_file(
            {k: v.contiguous() for k, v in dec.state_dict().items() if not k.endswith("num_batches_tracked")},
            str(out / "decoder.safetensors"),
        )

        image = torch.randint(0, 256, (args.height, args.width, 3), dtype=torch.uint8, generator=gen)
        x = image.permute(2, 0, 1).unsqueeze(0).float() / 255.0
        x = (x - torch.tensor(MEAN).view(1, 3, 1, 1)) / torch.tensor(STD).view(1, 3, 1, 1)
        save_file({"image": image.contiguous(), "input": x.contiguous()}, str(out / "input.safetensors"))

        with torch.no_grad():
            # As a batch of two copies: udapose runs a batch of one's small convolutions so
            # (engine/src/backbone/invariant.rs), because ATen sends them to other kernels that
            # round differently (resnet50's layer4 then differs by 2e-4 of values up to 64).
            l2, l3, l4 = (t[:1] for t in trunk(net, torch.cat([x, x])))
            feats = dec(l2, l3, l4)
            # The taps must be what torchvision's own forward computes on the way to fc.
            full = net.fc(torch.flatten(net.avgpool(l4), 1))
            assert torch.allclose(full, net(torch.cat([x, x]))[:1], rtol=0, atol=1e-5), "trunk() disagrees with torchvision's forward"
        ref = {"layer2": l2, "layer3": l3, "layer4": l4, "features": feats}
        save_file({k: v.contiguous() for k, v in ref.items()}, str(out / "reference.safetensors"))
        stats = ", ".join(f"{k} {tuple(v.shape)} max|x| {v.abs().max().item():.3g}" for k, v in ref.items())
        print(f"{arch}: {stats}")


if __name__ == "__main__":
    main()
