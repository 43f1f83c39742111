//! torchvision's AlexNet feature stack (the weights LPIPS's `net = "alex"`
//! uses), from the embedded weights (`vgg::weights`): five convolutions with
//! their ReLUs and the two 3x3 / stride-2 max-pools between the first three,
//! as torchvision's `alexnet().features` up to its last ReLU.
//!
//! Input: `[N, 3, H, W]` already normalised by the caller (LPIPS's scaling
//! layer); output: the five ReLU maps, in network order.

use burn::tensor::module::{conv2d, max_pool2d};
use burn::tensor::ops::{ConvOptions, MaxPoolOptions};
use burn::tensor::{Device, Tensor};

use crate::vgg::weights;

/// (stride, padding) of the five convolutions (kernels 11, 5, 3, 3, 3).
const GEOMETRY: [(usize, usize); 5] = [(4, 2), (1, 2), (1, 1), (1, 1), (1, 1)];

/// The smallest image side AlexNet takes: its fifth ReLU is then 1x1.
pub const MIN_SIDE: usize = 32;

/// The five convolutions' weights and biases.
#[derive(Debug, Clone)]
pub struct AlexNet {
    convs: Vec<(Tensor<4>, Tensor<1>)>,
}

impl AlexNet {
    /// torchvision's ImageNet weights (embedded), on `device`.
    pub fn load(device: &Device) -> Self {
        let convs = weights::LPIPS.convs("alex.", 5, device);
        Self { convs }
    }

    /// Channels of the five ReLU maps.
    pub const CHANNELS: [usize; 5] = [64, 192, 384, 256, 256];

    /// The five ReLU maps of `x`.
    pub fn features(&self, x: Tensor<4>) -> Vec<Tensor<4>> {
        let mut x = x;
        let mut out = Vec::with_capacity(5);
        for (i, ((w, b), (stride, pad))) in self.convs.iter().zip(GEOMETRY).enumerate() {
            // torchvision's pools sit after the first and the second ReLU.
            if i == 1 || i == 2 {
                x = max_pool2d(x, MaxPoolOptions::new([3, 3]).with_stride([2, 2]));
            }
            let options = ConvOptions::new([stride, stride], [pad, pad], [1, 1], 1);
            x = burn::tensor::activation::relu(conv2d(x, w.clone(), Some(b.clone()), options));
            out.push(x.clone());
        }
        out
    }
}
