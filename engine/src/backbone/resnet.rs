//! torchvision's ResNet trunk (v1.5: the stride is on the 3×3 conv), tapped at layer2/3/4.
//! Variable names are exactly torchvision's (`conv1.weight`, `layer2.0.downsample.1.running_var`,
//! ...), so a torchvision state dict loads unchanged.

use tch::Tensor;
use tch::nn::{self, Init};

use super::{Arch, bn, invariant};

/// torchvision's ResNet init: kaiming normal, fan out, ReLU gain.
pub(super) const CONV_INIT: Init = Init::Kaiming {
    dist: nn::init::NormalOrUniform::Normal,
    fan: nn::init::FanInOut::FanOut,
    non_linearity: nn::init::NonLinearity::ReLU,
};

/// Top-level names of the trunk's variables (torchvision's modules before avgpool/fc).
pub(super) const ROOTS: &[&str] = &["conv1", "bn1", "layer1", "layer2", "layer3", "layer4"];

fn conv(p: nn::Path, cin: i64, cout: i64, k: i64, stride: i64) -> nn::Conv2D {
    let cfg = nn::ConvConfig { stride, padding: k / 2, bias: false, ws_init: CONV_INIT, ..Default::default() };
    nn::conv2d(p, cin, cout, k, cfg)
}

/// Blocks per stage (layer1..layer4).
fn blocks(arch: Arch) -> [usize; 4] {
    match arch {
        Arch::ResNet18 => [2, 2, 2, 2],
        _ => [3, 4, 6, 3],
    }
}

fn expansion(arch: Arch) -> i64 {
    if arch == Arch::ResNet50 { 4 } else { 1 }
}

/// Channels of the layer2, layer3 and layer4 taps.
pub(super) fn tap_channels(arch: Arch) -> [i64; 3] {
    let e = expansion(arch);
    [128 * e, 256 * e, 512 * e]
}

/// A residual block, torchvision's BasicBlock or Bottleneck.
#[derive(Debug)]
struct Block {
    convs: Vec<(nn::Conv2D, nn::BatchNorm)>,
    downsample: Option<(nn::Conv2D, nn::BatchNorm)>,
}

impl Block {
    fn new(p: &nn::Path, arch: Arch, cin: i64, planes: i64, stride: i64) -> Block {
        let cout = planes * expansion(arch);
        let eps = 1e-5;
        let convs = if arch == Arch::ResNet50 {
            vec![
                (conv(p / "conv1", cin, planes, 1, 1), bn(p / "bn1", planes, eps)),
                (conv(p / "conv2", planes, planes, 3, stride), bn(p / "bn2", planes, eps)),
                (conv(p / "conv3", planes, cout, 1, 1), bn(p / "bn3", cout, eps)),
            ]
        } else {
            vec![
                (conv(p / "conv1", cin, planes, 3, stride), bn(p / "bn1", planes, eps)),
                (conv(p / "conv2", planes, cout, 3, 1), bn(p / "bn2", cout, eps)),
            ]
        };
        let downsample = (stride != 1 || cin != cout).then(|| {
            let d = p / "downsample";
            (conv(&d / "0", cin, cout, 1, stride), bn(&d / "1", cout, eps))
        });
        Block { convs, downsample }
    }

    fn forward_t(&self, x: &Tensor, train: bool) -> Tensor {
        let last = self.convs.len() - 1;
        let mut y = x.shallow_clone();
        for (i, (conv, norm)) in self.convs.iter().enumerate() {
            y = invariant::conv(&y, conv).apply_t(norm, train);
            if i < last {
                y = y.relu();
            }
        }
        let identity = match &self.downsample {
            Some((conv, norm)) => invariant::conv(x, conv).apply_t(norm, train),
            None => x.shallow_clone(),
        };
        (y + identity).relu()
    }
}

/// conv1 / bn1 / maxpool, then layer1..layer4.
#[derive(Debug)]
pub(super) struct ResNet {
    conv1: nn::Conv2D,
    bn1: nn::BatchNorm,
    layers: [Vec<Block>; 4],
}

impl ResNet {
    pub(super) fn new(path: &nn::Path, arch: Arch) -> ResNet {
        let conv1 = conv(path / "conv1", 3, 64, 7, 2);
        let bn1 = bn(path / "bn1", 64, 1e-5);
        let mut cin = 64;
        let mut stages = Vec::with_capacity(4);
        for (i, ((planes, stride), n)) in
            [(64, 1), (128, 2), (256, 2), (512, 2)].into_iter().zip(blocks(arch)).enumerate()
        {
            let stage = path / format!("layer{}", i + 1);
            let mut blocks = Vec::with_capacity(n);
            for b in 0..n {
                blocks.push(Block::new(&(&stage / b), arch, cin, planes, if b == 0 { stride } else { 1 }));
                cin = planes * expansion(arch);
            }
            stages.push(blocks);
        }
        ResNet { conv1, bn1, layers: stages.try_into().expect("four stages") }
    }

    /// layer2 (stride 8), layer3 (stride 16) and layer4 (stride 32) outputs.
    pub(super) fn forward_t(&self, x: &Tensor, train: bool) -> [Tensor; 3] {
        let x = x.apply(&self.conv1).apply_t(&self.bn1, train).relu().max_pool2d([3, 3], [2, 2], [1, 1], [1, 1], false);
        let run =
            |stage: &[Block], x: &Tensor| stage.iter().fold(x.shallow_clone(), |y, block| block.forward_t(&y, train));
        let l1 = run(&self.layers[0], &x);
        let l2 = run(&self.layers[1], &l1);
        let l3 = run(&self.layers[2], &l2);
        let l4 = run(&self.layers[3], &l3);
        [l2, l3, l4]
    }
}
