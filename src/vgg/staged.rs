//! VGG16's forward pass layer by layer: the imported graph's own modules
//! (input constants, convolutions, ReLUs, pools) in its order, stopping
//! after the deepest layer asked for. The losses need relu4_3 at most (TCM;
//! ARF relu3_3), and the generated `forward` always runs all 13
//! convolutions; stage 5 is about 9 % of the forward's multiply-adds.

use burn::tensor::Tensor;

use crate::kernels::conv_op::{PreparedSlot, conv3x3_relu_forward};
use crate::vgg::VggLayer;
use crate::vgg::model::Model;

/// The ReLU outputs of `model` up to the deepest of `layers`, in network
/// order (13 entries, `None` past the deepest).
/// With `prepared` (slots for the first convolutions) the 3x3 convolutions
/// run through `kernels::conv_op` (on the CPU backends, with the slots'
/// prepared weights where there is a slot; Burn's `conv2d` elsewhere),
/// without it through Burn's `conv2d`.
pub fn forward(
    model: &Model,
    image: Tensor<4>,
    layers: &[VggLayer],
    prepared: Option<&[PreparedSlot]>,
) -> Vec<Option<Tensor<4>>> {
    let deepest = layers.iter().map(|l| l.index()).max().unwrap_or(0);
    let (scale, mean) = model.input_constants();
    let mut x = image.mul(scale.unsqueeze_dims(&[0, 1, 2])).sub(mean);
    let (convs, pools) = (model.convs(), model.pools());
    let mut out = vec![None; 13];
    for (i, conv) in convs.iter().enumerate().take(deepest + 1) {
        // A pool sits before the first convolution of stages 2 to 5.
        if let Some(p) = [2, 4, 7, 10].iter().position(|&first| first == i) {
            x = pools[p].forward(x);
        }
        x = match prepared {
            Some(slots) => conv3x3_relu_forward(conv, x, slots.get(i)),
            None => burn::tensor::activation::relu(conv.forward(x)),
        };
        out[i] = Some(x.clone());
    }
    out
}
