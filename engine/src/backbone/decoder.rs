//! NeMo's "resnetext" decoder (METHOD.md §4): DoubleConv on the stride-32 tap, two Up blocks
//! (bilinear, align_corners, concatenate `[tap, upsampled]`, DoubleConv), a 1×1 convolution to D
//! without bias and per-pixel L2 normalisation. Names are NeMo's:
//! `upsample0.doubleconv.{0,1,3,4}.*`, `upsample{1,2}.doubleconv.doubleconv.{0,1,3,4}.*` (0 and 3
//! the 3×3 convolutions with bias, 1 and 4 their BatchNorms) and `out_layer.weight`.

use tch::nn::{self, Init};
use tch::{Kind, Tensor};

use super::invariant::{conv, conv_with};
use super::{DecoderWidths, bn};

/// L2 normalisation floor, as `torch.nn.functional.normalize`.
const NORM_EPS: f64 = 1e-12;

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
        let cfg =
            nn::ConvConfig { padding: 1, bias: true, ws_init: nn::init::DEFAULT_KAIMING_UNIFORM, ..Default::default() };
        DoubleConv {
            conv_a: nn::conv2d(&p / "0", cin, mid, 3, cfg),
            bn_a: bn(&p / "1", mid, 1e-5),
            conv_b: nn::conv2d(&p / "3", mid, cout, 3, cfg),
            bn_b: bn(&p / "4", cout, 1e-5),
        }
    }

    fn forward_t(&self, x: &Tensor, train: bool) -> Tensor {
        let y = conv(x, &self.conv_a).apply_t(&self.bn_a, train).relu();
        conv(&y, &self.conv_b).apply_t(&self.bn_b, train).relu()
    }

    /// Bilinear upsampling (align_corners) of `x` to the tap's size (×2 for inputs that are
    /// multiples of 32), concatenation `[tap, upsampled]`, DoubleConv.
    fn up(&self, x: &Tensor, tap: &Tensor, train: bool) -> Tensor {
        let (h, w) = (tap.size()[2], tap.size()[3]);
        let x = x.upsample_bilinear2d([h, w], true, None, None);
        self.forward_t(&Tensor::cat(&[tap, &x], 1), train)
    }
}

#[derive(Debug)]
pub(super) struct Decoder {
    upsample0: DoubleConv,
    upsample1: DoubleConv,
    upsample2: DoubleConv,
    out_layer: Tensor,
}

impl Decoder {
    /// Decoder convs kaiming uniform, BN 1/0, the 1×1 as torch.nn.Conv2d's default.
    pub(super) fn new(path: &nn::Path, w: DecoderWidths, dim: i64) -> Decoder {
        let upsample0 =
            DoubleConv::new(path / "upsample0" / "doubleconv", w.double_conv.0, w.double_conv.1, w.double_conv.1);
        let upsample1 = DoubleConv::new(path / "upsample1" / "doubleconv" / "doubleconv", w.up1.0, w.up1.1, w.up1.2);
        let upsample2 = DoubleConv::new(path / "upsample2" / "doubleconv" / "doubleconv", w.up2.0, w.up2.1, w.up2.2);
        // As torch.nn.Conv2d's default: U(±1/sqrt(fan_in)).
        let out_init = Init::Kaiming {
            dist: nn::init::NormalOrUniform::Uniform,
            fan: nn::init::FanInOut::FanIn,
            non_linearity: nn::init::NonLinearity::ExplicitGain(1.0 / 3f64.sqrt()),
        };
        let out_layer = (path / "out_layer").var("weight", &[dim, w.up2.2, 1, 1], out_init);
        Decoder { upsample0, upsample1, upsample2, out_layer }
    }

    /// Unit-norm N×D features at the stride-8 tap's size.
    pub(super) fn forward_t(&self, [t8, t16, t32]: &[Tensor; 3], train: bool) -> Tensor {
        let y = self.upsample0.forward_t(t32, train);
        let y = self.upsample1.up(&y, t16, train);
        let y = self.upsample2.up(&y, t8, train);
        let y =
            conv_with(&y, &self.out_layer, |y| y.conv2d(&self.out_layer, None::<Tensor>, [1, 1], [0, 0], [1, 1], 1));
        // sqrt(Σy² + ε²), not max(‖y‖, ε): the norm's gradient is 0/0 at a zero vector, which
        // fine-tuning can reach (a pixel whose decoder activations all die).
        let norm = (y.square().sum_dim_intlist([1i64].as_slice(), true, Kind::Float) + NORM_EPS * NORM_EPS).sqrt();
        y / norm
    }
}
