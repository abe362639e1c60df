#!/usr/bin/env python3
"""Exports a torchvision ResNet state dict as safetensors for udapose's backbone (METHOD.md §4).

    python lab/scripts/export_torchvision.py --arch resnet50 --state-dict resnet50-imagenet.pth --out r50.safetensors
    python lab/scripts/export_torchvision.py --arch resnet18 --random-seed 0 --out r18-random.safetensors

The model is always built with `torchvision.models.<arch>(weights=None)`: nothing is downloaded.
With --state-dict, the weights of that file (a torchvision ResNet state dict a user provides, e.g.
the ImageNet one saved from a machine with network access) are loaded strictly, so a file of
another architecture fails here rather than in udapose; a checkpoint that wraps the state dict
under "state_dict" or "model", or prefixes every key with "module." (DataParallel), is unwrapped.
Without it the model keeps torchvision's random initialisation, seeded by --random-seed.

Every tensor of the state dict is written under torchvision's name (conv1.weight, bn1.running_mean,
layer2.0.downsample.1.weight, fc.weight, ...), floating-point tensors as float32. The integer
BatchNorm counters `*.num_batches_tracked` are kept as int64 unless --drop-num-batches-tracked;
udapose's loader (`Backbone::load_torchvision`) accepts both and ignores them, and ignores fc.*.

Use the project venv's python (`make test` installs torchvision==0.28.0 and safetensors there).
"""

import argparse
import sys
from pathlib import Path

ARCHS = ("resnet18", "resnet34", "resnet50")


def build(arch, seed=0):
    """A torchvision ResNet with random (seeded) initialisation; never downloads weights."""
    import torch
    import torchvision

    if arch not in ARCHS:
        raise ValueError(f"unknown arch {arch!r}; expected one of {', '.join(ARCHS)}")
    torch.manual_seed(seed)
    return getattr(torchvision.models, arch)(weights=None)


def read_state_dict(path):
    """A state dict from a .pth/.pt file (or a .safetensors file), unwrapped as described above."""
    import torch

    path = Path(path)
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        state = load_file(str(path))
    else:
        state = torch.load(str(path), map_location="cpu", weights_only=True)
    for wrapper in ("state_dict", "model"):
        if isinstance(state, dict) and wrapper in state and isinstance(state[wrapper], dict):
            state = state[wrapper]
    if not isinstance(state, dict):
        raise ValueError(f"{path}: expected a state dict, found {type(state).__name__}")
    if state and all(k.startswith("module.") for k in state):
        state = {k[len("module.") :]: v for k, v in state.items()}
    return state


def export_state_dict(state, out, drop_num_batches_tracked=False):
    """Writes `state` (name -> tensor) to `out` as safetensors: floats as float32, ints as int64."""
    import torch
    from safetensors.torch import save_file

    tensors = {}
    for name, t in state.items():
        if name.endswith("num_batches_tracked"):
            if drop_num_batches_tracked:
                continue
            tensors[name] = t.detach().to(torch.int64).contiguous().clone()
        elif t.is_floating_point():
            tensors[name] = t.detach().to(torch.float32).contiguous().clone()
        else:
            raise ValueError(f"{name}: unexpected non-float tensor of dtype {t.dtype}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_file(tensors, str(out), metadata={"format": "pt", "source": "torchvision"})
    return tensors


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--arch", required=True, choices=ARCHS)
    ap.add_argument("--state-dict", type=Path, help="torchvision state dict (.pth/.pt/.safetensors) to export")
    ap.add_argument("--random-seed", type=int, default=0, help="seed of the random init when no --state-dict")
    ap.add_argument("--drop-num-batches-tracked", action="store_true", help="leave out *.num_batches_tracked")
    ap.add_argument("--out", required=True, type=Path, help="output .safetensors file")
    args = ap.parse_args(argv)

    try:
        import safetensors  # noqa: F401
        import torch  # noqa: F401
        import torchvision  # noqa: F401
    except ImportError as e:
        sys.exit(
            f"export_torchvision.py: {e}. This needs torch, torchvision and safetensors in {sys.executable}; "
            "`make test` installs the pinned versions into the project venv."
        )

    model = build(args.arch, args.random_seed)
    if args.state_dict is not None:
        try:
            model.load_state_dict(read_state_dict(args.state_dict), strict=True)
        except (RuntimeError, ValueError) as e:
            sys.exit(f"export_torchvision.py: {args.state_dict} is not a torchvision {args.arch} state dict: {e}")
    tensors = export_state_dict(model.state_dict(), args.out, args.drop_num_batches_tracked)
    params = sum(t.numel() for n, t in tensors.items() if t.is_floating_point())
    source = args.state_dict if args.state_dict is not None else f"random init, seed {args.random_seed}"
    print(f"{args.arch} ({source}): {len(tensors)} tensors, {params} floats -> {args.out}")


if __name__ == "__main__":
    main()
