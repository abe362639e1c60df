//! The feature backbone (METHOD.md §4): a torchvision ResNet trunk tapped at layer2/3/4 and NeMo's
//! "resnetext" decoder, giving unit-norm D-dimensional features at stride 8.
//!
//! Variable names under the `nn::Path` the backbone is built on:
//!
//! - trunk: exactly torchvision's (`conv1.weight`, `bn1.running_mean`, `layer1.0.conv1.weight`,
//!   `layer2.0.downsample.0.weight`, `layer2.0.downsample.1.running_var`, ...), so a torchvision
//!   state dict exported by `lab/scripts/export_torchvision.py` loads unchanged
//!   ([`Backbone::load_torchvision`]). BatchNorm's `num_batches_tracked` counter has no variable:
//!   tch's BatchNorm uses a fixed momentum, so the counter is never read; the loader ignores it.
//! - decoder: NeMo's module names, `upsample0.doubleconv.{0,1,3,4}.*` (DoubleConv on layer4),
//!   `upsample{1,2}.doubleconv.doubleconv.{0,1,3,4}.*` (the Up blocks; 0 and 3 are the 3×3
//!   convolutions, with bias as in NeMo, 1 and 4 their BatchNorms) and `out_layer.weight`
//!   (the 1×1 convolution to D, D×C×1×1, no bias).
//!
//! Threading (ARCHITECTURE.md "Threading with tch"): a `Backbone` and its `VarStore` belong to one
//! thread at a time; train mode updates the BatchNorm running statistics in place. This module
//! never sets libtorch's thread count.

use std::collections::BTreeMap;
use std::fmt;
use std::path::Path;
use std::str::FromStr;

use serde::{Deserialize, Serialize};
use tch::nn::{self, Init};
use tch::{Kind, Tensor};

use crate::error::{EngineError, Result};

/// ImageNet channel means (RGB, for inputs scaled to [0, 1]), as torchvision normalises.
pub const IMAGENET_MEAN: [f64; 3] = [0.485, 0.456, 0.406];
/// ImageNet channel standard deviations (RGB).
pub const IMAGENET_STD: [f64; 3] = [0.229, 0.224, 0.225];
/// Output stride of the features: an N×3×H×W input gives N×D×(H/8)×(W/8).
pub const STRIDE: i64 = 8;
/// Input sides NeMo uses are multiples of this (the trunk's total stride); other multiples of
/// [`STRIDE`] also work, the Up blocks resize to the tap's exact size.
pub const INPUT_MULTIPLE: i64 = 32;
/// Default feature dimension D.
pub const DEFAULT_DIM: i64 = 128;
/// L2 normalisation floor, as `torch.nn.functional.normalize`.
const NORM_EPS: f64 = 1e-12;
/// Top-level names of the trunk's variables (torchvision's modules before avgpool/fc).
const TRUNK_ROOTS: [&str; 6] = ["conv1", "bn1", "layer1", "layer2", "layer3", "layer4"];

/// Which torchvision ResNet the trunk is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Arch {
    ResNet18,
    ResNet34,
    ResNet50,
}

/// Channel widths of the decoder for one trunk (METHOD.md §4 table).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DecoderWidths {
    /// DoubleConv on layer4: (in, out); its middle width is `out`.
    pub double_conv: (i64, i64),
    /// First Up block (on layer3): (in, mid, out); `in` = layer3 width + `double_conv.1`.
    pub up1: (i64, i64, i64),
    /// Second Up block (on layer2): (in, mid, out); `in` = layer2 width + `up1.2`.
    pub up2: (i64, i64, i64),
}

impl Arch {
    pub const ALL: [Arch; 3] = [Arch::ResNet18, Arch::ResNet34, Arch::ResNet50];

    /// torchvision's name: "resnet18", "resnet34", "resnet50".
    pub fn name(self) -> &'static str {
        match self {
            Arch::ResNet18 => "resnet18",
            Arch::ResNet34 => "resnet34",
            Arch::ResNet50 => "resnet50",
        }
    }

    /// Blocks per stage (layer1..layer4).
    pub fn blocks(self) -> [usize; 4] {
        match self {
            Arch::ResNet18 => [2, 2, 2, 2],
            Arch::ResNet34 | Arch::ResNet50 => [3, 4, 6, 3],
        }
    }

    /// Bottleneck blocks (expansion 4) rather than BasicBlocks (expansion 1).
    pub fn bottleneck(self) -> bool {
        self == Arch::ResNet50
    }

    fn expansion(self) -> i64 {
        if self.bottleneck() { 4 } else { 1 }
    }

    /// Channels of the layer2, layer3 and layer4 taps.
    pub fn tap_channels(self) -> [i64; 3] {
        let e = self.expansion();
        [128 * e, 256 * e, 512 * e]
    }

    /// Decoder widths: the METHOD.md §4 table.
    pub fn decoder_widths(self) -> DecoderWidths {
        match self {
            Arch::ResNet50 => {
                DecoderWidths { double_conv: (2048, 1024), up1: (2048, 1024, 512), up2: (1024, 512, 256) }
            }
            Arch::ResNet18 | Arch::ResNet34 => {
                DecoderWidths { double_conv: (512, 256), up1: (512, 256, 128), up2: (256, 128, 64) }
            }
        }
    }
}

impl fmt::Display for Arch {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Arch {
    type Err = EngineError;

    /// "resnet18", "resnet34", "resnet50" (case-insensitive; "resnet-50" and "resnet_50" too).
    fn from_str(s: &str) -> Result<Self> {
        let norm: String = s.trim().to_ascii_lowercase().chars().filter(|c| !matches!(c, '-' | '_')).collect();
        Arch::ALL.into_iter().find(|a| a.name() == norm).ok_or_else(|| {
            EngineError::InvalidInput(format!(
                "unknown backbone architecture {s:?}: expected resnet18, resnet34 or resnet50"
            ))
        })
    }
}

fn conv_cfg(stride: i64, padding: i64, bias: bool, ws_init: Init) -> nn::ConvConfig {
    nn::ConvConfig { stride, padding, bias, ws_init, ..Default::default() }
}

/// torchvision's ResNet init: kaiming normal, fan out, ReLU gain.
const TRUNK_CONV_INIT: Init = Init::Kaiming {
    dist: nn::init::NormalOrUniform::Normal,
    fan: nn::init::FanInOut::FanOut,
    non_linearity: nn::init::NonLinearity::ReLU,
};

/// BatchNorm's running-statistics momentum (torch.nn.BatchNorm2d's).
const BN_MOMENTUM: f64 = 0.1;

/// BatchNorm as torch.nn.BatchNorm2d: weight 1, bias 0, eps 1e-5, momentum 0.1.
fn bn(p: nn::Path, c: i64) -> nn::BatchNorm {
    let cfg = nn::BatchNormConfig {
        ws_init: Init::Const(1.0),
        bs_init: Init::Const(0.0),
        momentum: BN_MOMENTUM,
        ..Default::default()
    };
    nn::batch_norm2d(p, c, cfg)
}

fn trunk_conv(p: nn::Path, cin: i64, cout: i64, k: i64, stride: i64) -> nn::Conv2D {
    nn::conv2d(p, cin, cout, k, conv_cfg(stride, k / 2, false, TRUNK_CONV_INIT))
}

/// A residual block, torchvision's BasicBlock or Bottleneck (v1.5: the stride is on the 3×3 conv2).
#[derive(Debug)]
struct Block {
    convs: Vec<(nn::Conv2D, nn::BatchNorm)>,
    downsample: Option<(nn::Conv2D, nn::BatchNorm)>,
}

impl Block {
    fn new(p: &nn::Path, arch: Arch, cin: i64, planes: i64, stride: i64) -> Block {
        let cout = planes * arch.expansion();
        let convs = if arch.bottleneck() {
            vec![
                (trunk_conv(p / "conv1", cin, planes, 1, 1), bn(p / "bn1", planes)),
                (trunk_conv(p / "conv2", planes, planes, 3, stride), bn(p / "bn2", planes)),
                (trunk_conv(p / "conv3", planes, cout, 1, 1), bn(p / "bn3", cout)),
            ]
        } else {
            vec![
                (trunk_conv(p / "conv1", cin, planes, 3, stride), bn(p / "bn1", planes)),
                (trunk_conv(p / "conv2", planes, cout, 3, 1), bn(p / "bn2", cout)),
            ]
        };
        let downsample = (stride != 1 || cin != cout).then(|| {
            let d = p / "downsample";
            (trunk_conv(&d / "0", cin, cout, 1, stride), bn(&d / "1", cout))
        });
        Block { convs, downsample }
    }

    fn forward_t(&self, x: &Tensor, train: bool) -> Tensor {
        let last = self.convs.len() - 1;
        let mut y = x.shallow_clone();
        for (i, (conv, norm)) in self.convs.iter().enumerate() {
            y = y.apply(conv).apply_t(norm, train);
            if i < last {
                y = y.relu();
            }
        }
        let identity = match &self.downsample {
            Some((conv, norm)) => x.apply(conv).apply_t(norm, train),
            None => x.shallow_clone(),
        };
        (y + identity).relu()
    }
}

/// (3×3 conv pad 1 with bias, BN, ReLU) × 2 through `mid` channels; NeMo's `doubleconv`
/// Sequential, so the variables are `0.*`, `1.*`, `3.*`, `4.*`.
#[derive(Debug)]
struct DoubleConv {
    conv_a: nn::Conv2D,
    bn_a: nn::BatchNorm,
    conv_b: nn::Conv2D,
    bn_b: nn::BatchNorm,
}

impl DoubleConv {
    fn new(p: nn::Path, cin: i64, mid: i64, cout: i64) -> DoubleConv {
        let init = nn::init::DEFAULT_KAIMING_UNIFORM;
        DoubleConv {
            conv_a: nn::conv2d(&p / "0", cin, mid, 3, conv_cfg(1, 1, true, init)),
            bn_a: bn(&p / "1", mid),
            conv_b: nn::conv2d(&p / "3", mid, cout, 3, conv_cfg(1, 1, true, init)),
            bn_b: bn(&p / "4", cout),
        }
    }

    fn forward_t(&self, x: &Tensor, train: bool) -> Tensor {
        x.apply(&self.conv_a).apply_t(&self.bn_a, train).relu().apply(&self.conv_b).apply_t(&self.bn_b, train).relu()
    }
}

/// Bilinear upsampling (align_corners) of `x` to the tap's size (×2 for inputs that are multiples
/// of 32), concatenation `[tap, upsampled]`, DoubleConv.
fn up(conv: &DoubleConv, x: &Tensor, tap: &Tensor, train: bool) -> Tensor {
    let (h, w) = (tap.size()[2], tap.size()[3]);
    let x = x.upsample_bilinear2d([h, w], true, None, None);
    conv.forward_t(&Tensor::cat(&[tap, &x], 1), train)
}

/// What [`Backbone::load_torchvision`] did.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TorchvisionLoad {
    /// Trunk tensors copied (every trunk variable of the backbone).
    pub loaded: usize,
    /// Keys of the file that were skipped: `fc.*` and `*.num_batches_tracked`.
    pub ignored: Vec<String>,
}

/// The backbone: ResNet trunk + resnetext decoder + 1×1 projection + per-pixel L2 normalisation.
#[derive(Debug)]
pub struct Backbone {
    arch: Arch,
    dim: i64,
    /// Dotted name of the `nn::Path` it was built on ("" for the root).
    prefix: String,
    conv1: nn::Conv2D,
    bn1: nn::BatchNorm,
    layers: [Vec<Block>; 4],
    upsample0: DoubleConv,
    upsample1: DoubleConv,
    upsample2: DoubleConv,
    out_layer: Tensor,
}

impl Backbone {
    /// Creates the variables under `path` (trunk names as torchvision's, see the module docs),
    /// randomly initialised: trunk as torchvision, decoder convs kaiming uniform, BN 1/0.
    pub fn new(path: nn::Path, arch: Arch, dim: i64) -> Backbone {
        assert!(dim > 0, "feature dimension must be positive, got {dim}");
        let prefix = path.components().collect::<Vec<_>>().join(".");
        let conv1 = trunk_conv(&path / "conv1", 3, 64, 7, 2);
        let bn1 = bn(&path / "bn1", 64);
        let mut cin = 64;
        let mut stages = Vec::with_capacity(4);
        for (i, ((planes, stride), n)) in
            [(64, 1), (128, 2), (256, 2), (512, 2)].into_iter().zip(arch.blocks()).enumerate()
        {
            let stage = &path / format!("layer{}", i + 1);
            let mut blocks = Vec::with_capacity(n);
            for b in 0..n {
                blocks.push(Block::new(&(&stage / b), arch, cin, planes, if b == 0 { stride } else { 1 }));
                cin = planes * arch.expansion();
            }
            stages.push(blocks);
        }
        let layers: [Vec<Block>; 4] = stages.try_into().expect("four stages");
        let w = arch.decoder_widths();
        let upsample0 =
            DoubleConv::new(&path / "upsample0" / "doubleconv", w.double_conv.0, w.double_conv.1, w.double_conv.1);
        let upsample1 = DoubleConv::new(&path / "upsample1" / "doubleconv" / "doubleconv", w.up1.0, w.up1.1, w.up1.2);
        let upsample2 = DoubleConv::new(&path / "upsample2" / "doubleconv" / "doubleconv", w.up2.0, w.up2.1, w.up2.2);
        // As torch.nn.Conv2d's default: U(±1/sqrt(fan_in)).
        let out_init = Init::Kaiming {
            dist: nn::init::NormalOrUniform::Uniform,
            fan: nn::init::FanInOut::FanIn,
            non_linearity: nn::init::NonLinearity::ExplicitGain(1.0 / 3f64.sqrt()),
        };
        let out_layer = (&path / "out_layer").var("weight", &[dim, w.up2.2, 1, 1], out_init);
        Backbone { arch, dim, prefix, conv1, bn1, layers, upsample0, upsample1, upsample2, out_layer }
    }

    pub fn arch(&self) -> Arch {
        self.arch
    }

    /// Feature dimension D.
    pub fn dim(&self) -> i64 {
        self.dim
    }

    /// The trunk's taps: layer2 (stride 8), layer3 (stride 16), layer4 (stride 32) outputs for a
    /// normalised N×3×H×W input (see [`preprocess`]).
    pub fn trunk(&self, x: &Tensor, train: bool) -> [Tensor; 3] {
        let x = x.apply(&self.conv1).apply_t(&self.bn1, train).relu().max_pool2d([3, 3], [2, 2], [1, 1], [1, 1], false);
        let run =
            |stage: &[Block], x: &Tensor| stage.iter().fold(x.shallow_clone(), |y, block| block.forward_t(&y, train));
        let l1 = run(&self.layers[0], &x);
        let l2 = run(&self.layers[1], &l1);
        let l3 = run(&self.layers[2], &l2);
        let l4 = run(&self.layers[3], &l3);
        [l2, l3, l4]
    }

    /// Unit-norm features N×D×(H/8)×(W/8) for a normalised N×3×H×W input (H, W multiples of 8;
    /// NeMo uses multiples of 32). Panics (inside libtorch) on a malformed input: use
    /// [`Backbone::features`] for untrusted shapes.
    pub fn forward_t(&self, x: &Tensor, train: bool) -> Tensor {
        let [l2, l3, l4] = self.trunk(x, train);
        let y = self.upsample0.forward_t(&l4, train);
        let y = up(&self.upsample1, &y, &l3, train);
        let y = up(&self.upsample2, &y, &l2, train);
        let y = y.conv2d(&self.out_layer, None::<Tensor>, [1, 1], [0, 0], [1, 1], 1);
        // sqrt(Σy² + ε²), not max(‖y‖, ε): the norm's gradient is 0/0 at a zero vector, which
        // fine-tuning can reach (a pixel whose decoder activations all die).
        let norm = (y.square().sum_dim_intlist([1i64].as_slice(), true, Kind::Float) + NORM_EPS * NORM_EPS).sqrt();
        y / norm
    }

    /// [`Backbone::forward_t`] after checking the input: 4-D, 3 channels, floating point, sides
    /// at least [`INPUT_MULTIPLE`].
    pub fn features(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        check_input(x)?;
        Ok(self.forward_t(x, train))
    }

    /// Loads a torchvision ResNet state dict exported as safetensors by
    /// `lab/scripts/export_torchvision.py` into the trunk of this backbone, which must live in
    /// `vs`. The decoder keeps its values. `fc.*` (the classifier) and `*.num_batches_tracked`
    /// (int64 or absent) are ignored; every other key must be a trunk variable of this backbone
    /// with the same shape, and every trunk variable must be present. Tensors of any floating
    /// kind are converted to the variables' kind and device. All checks run before anything is
    /// written, so on error the weights are unchanged.
    ///
    /// Writes into the variables in place: never call it on weights a worker is serving with.
    pub fn load_torchvision(&self, vs: &mut nn::VarStore, file: impl AsRef<Path>) -> Result<TorchvisionLoad> {
        let file = file.as_ref();
        let tensors = crate::checkpoint::read_tensors(file)?;

        // This backbone's trunk variables, by torchvision name (the path prefix stripped).
        let strip = if self.prefix.is_empty() { 0 } else { self.prefix.len() + 1 };
        let trunk: BTreeMap<String, Tensor> = vs
            .variables()
            .into_iter()
            .filter_map(|(name, t)| {
                if strip > 0 && !(name.starts_with(&self.prefix) && name[self.prefix.len()..].starts_with('.')) {
                    return None;
                }
                let key = &name[strip..];
                let root = key.split('.').next()?;
                TRUNK_ROOTS.contains(&root).then(|| (key.to_string(), t))
            })
            .collect();
        if trunk.is_empty() {
            return Err(EngineError::InvalidInput(format!(
                "the var store has no trunk variables under {:?}: was the backbone built on it?",
                self.prefix
            )));
        }

        // The classifier and BatchNorm's batch counters are not part of udapose's trunk.
        let (ignored, kept): (Vec<_>, Vec<_>) =
            tensors.into_iter().partition(|(key, _)| key.starts_with("fc.") || key.ends_with("num_batches_tracked"));
        let mut ignored: Vec<String> = ignored.into_iter().map(|(key, _)| key).collect();
        ignored.sort();
        let found: BTreeMap<String, Tensor> = kept.into_iter().collect();
        let loaded = found.len();
        crate::checkpoint::copy_checked(file, &trunk, found)?;
        Ok(TorchvisionLoad { loaded, ignored })
    }

    /// Replaces every BatchNorm's running mean and variance by their average over `images`
    /// (N×3×H×W RGB in [0, 1]) in batches of `batch` (AdaBN). Learned scales and shifts are
    /// kept. tch's BatchNorm only offers a fixed-momentum EMA, so each batch's statistics are
    /// recovered from the running value before and after its train-mode forward. Returns the
    /// number of statistics tensors replaced. The backbone must live in `vs`.
    pub fn reestimate_batchnorm(&self, vs: &nn::VarStore, images: &Tensor, batch: usize) -> Result<usize> {
        let n = images.size().first().copied().unwrap_or(0);
        if n == 0 || batch == 0 {
            return Err(EngineError::InvalidInput("BatchNorm statistics need at least one image".into()));
        }
        let own = |name: &str| self.prefix.is_empty() || name.starts_with(&format!("{}.", self.prefix));
        let stats: Vec<Tensor> = vs
            .variables()
            .into_iter()
            .filter(|(name, _)| own(name) && (name.ends_with(".running_mean") || name.ends_with(".running_var")))
            .map(|(_, t)| t)
            .collect();
        let _no_grad = tch::no_grad_guard();
        let mut sums: Vec<Tensor> = stats.iter().map(Tensor::zeros_like).collect();
        let mut batches = 0i64;
        for start in (0..n).step_by(batch) {
            let x = images.narrow(0, start, (batch as i64).min(n - start)).to_device(vs.device());
            let before: Vec<Tensor> = stats.iter().map(Tensor::copy).collect();
            let _ = self.forward_t(&preprocess(&x)?, true);
            for ((sum, now), old) in sums.iter_mut().zip(&stats).zip(&before) {
                *sum += (now - old * (1.0 - BN_MOMENTUM)) / BN_MOMENTUM;
            }
            batches += 1;
        }
        for (mut t, sum) in stats.iter().map(Tensor::shallow_clone).zip(&sums) {
            t.copy_(&(sum / batches as f64));
        }
        Ok(stats.len())
    }
}

impl nn::ModuleT for Backbone {
    fn forward_t(&self, xs: &Tensor, train: bool) -> Tensor {
        Backbone::forward_t(self, xs, train)
    }
}

/// Checks a backbone input: N×3×H×W floating point with H, W ≥ [`INPUT_MULTIPLE`].
pub fn check_input(x: &Tensor) -> Result<()> {
    let size = x.size();
    if size.len() != 4 || size[1] != 3 || size[0] < 1 {
        return Err(EngineError::InvalidInput(format!("backbone input must be N x 3 x H x W, got {size:?}")));
    }
    if size[2] < INPUT_MULTIPLE || size[3] < INPUT_MULTIPLE {
        return Err(EngineError::InvalidInput(format!(
            "backbone input {}x{} is smaller than {INPUT_MULTIPLE}x{INPUT_MULTIPLE}",
            size[3], size[2]
        )));
    }
    if !x.is_floating_point() {
        return Err(EngineError::InvalidInput(format!("backbone input must be floating point, got {:?}", x.kind())));
    }
    Ok(())
}

/// ImageNet normalisation, torchvision style: `(x / 255 - mean) / std` for u8 images in HWC
/// layout (H×W×3 or N×H×W×3), `(x - mean) / std` for floating-point images in [0, 1] in CHW
/// layout (3×H×W or N×3×H×W). Returns an N×3×H×W float tensor on the input's device.
pub fn preprocess(image: &Tensor) -> Result<Tensor> {
    let size = image.size();
    let x = match image.kind() {
        Kind::Uint8 => {
            let x = match size.as_slice() {
                [_, _, 3] => image.unsqueeze(0),
                [_, _, _, 3] => image.shallow_clone(),
                _ => {
                    return Err(EngineError::InvalidInput(format!(
                        "u8 image must be H x W x 3 or N x H x W x 3, got {size:?}"
                    )));
                }
            };
            x.permute([0, 3, 1, 2]).to_kind(Kind::Float) / 255.0
        }
        Kind::Float | Kind::Double | Kind::Half | Kind::BFloat16 => match size.as_slice() {
            [3, _, _] => image.unsqueeze(0).to_kind(Kind::Float),
            [_, 3, _, _] => image.to_kind(Kind::Float),
            _ => {
                return Err(EngineError::InvalidInput(format!(
                    "float image must be 3 x H x W or N x 3 x H x W, got {size:?}"
                )));
            }
        },
        kind => return Err(EngineError::InvalidInput(format!("image must be u8 or floating point, got {kind:?}"))),
    };
    let s = x.size();
    if s[0] == 0 || s[2] == 0 || s[3] == 0 {
        return Err(EngineError::EmptyImage { width: s[3] as usize, height: s[2] as usize });
    }
    let opts = (Kind::Float, x.device());
    let mean = Tensor::from_slice(&IMAGENET_MEAN).to_kind(opts.0).to_device(opts.1).view([1, 3, 1, 1]);
    let std = Tensor::from_slice(&IMAGENET_STD).to_kind(opts.0).to_device(opts.1).view([1, 3, 1, 1]);
    Ok((x - mean) / std)
}

/// [`preprocess`] for packed RGB8 pixels (row-major, `width * height * 3` bytes, as
/// `image::RgbImage::as_raw`): a 1×3×H×W float tensor on the CPU.
pub fn preprocess_rgb8(pixels: &[u8], width: usize, height: usize) -> Result<Tensor> {
    if width == 0 || height == 0 {
        return Err(EngineError::EmptyImage { width, height });
    }
    if pixels.len() != width * height * 3 {
        return Err(EngineError::InvalidInput(format!(
            "{} bytes for a {width}x{height} RGB8 image (expected {})",
            pixels.len(),
            width * height * 3
        )));
    }
    preprocess(&Tensor::from_slice(pixels).view([height as i64, width as i64, 3]))
}
