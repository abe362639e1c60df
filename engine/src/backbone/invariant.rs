//! Convolutions whose per-image results do not depend on the batch size.
//!
//! ATen picks a convolution's kernels by shape (`ConvParams::use_mkldnn`, libtorch 2.13): on
//! the CPU a batch of *one* whose convolution is small (groups 1, kernel at most 3×3, at most
//! 20,480 input values) goes to its native kernels, every larger batch to oneDNN's, and the two
//! round differently (≤ 6e-7 relative on the features, enough to move an answer by 10° where the
//! loss is flat). oneDNN's results per image do not depend on the batch (measured by
//! `bench/examples/batch_invariance.rs`), so such a convolution of one image runs as a batch of
//! two copies: the late, low-resolution layers only (a lone crop's pass +9% at one thread,
//! measured with A/B builds of that example).

use tch::nn;
use tch::{Device, Tensor};

/// The most input values of a batch-of-one convolution ATen still sends to its native kernels.
const NATIVE_MAX_VALUES: i64 = 20_480;

/// `layer(x)` for a convolution with weights `weight` (O × I/groups × kh × kw), computed as in a
/// batch of two where ATen would take its batch-of-one kernels.
pub(super) fn conv_with(x: &Tensor, weight: &Tensor, layer: impl Fn(&Tensor) -> Tensor) -> Tensor {
    let (xs, ws) = (x.size(), weight.size());
    let native = xs.len() == 4
        && ws.len() == 4
        && xs[0] == 1
        && x.device() == Device::Cpu
        && ws[1] == xs[1] // groups 1
        && ws[2] <= 3
        && ws[3] <= 3
        && xs[1] * xs[2] * xs[3] <= NATIVE_MAX_VALUES;
    if native { layer(&x.repeat([2, 1, 1, 1])).narrow(0, 0, 1) } else { layer(x) }
}

/// `x.apply(conv)`, batch-invariant.
pub(super) fn conv(x: &Tensor, conv: &nn::Conv2D) -> Tensor {
    conv_with(x, &conv.ws, |x| x.apply(conv))
}
