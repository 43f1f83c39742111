//! VGG16's forward pass with each 3x3 convolution written as one matrix
//! product (im2col: the nine shifted copies of the padded input stacked
//! along channels, times the weights as a `[out, in x 9]` matrix), from the
//! imported model's own weights, bias and input constants.
//!
//! Why: on the CPU backends Burn's convolution backward (the gradient with
//! respect to the input goes through a transposed convolution) dominates a
//! stylization step. Written as tensor operations, autodiff differentiates
//! a matrix product (one more matrix product, on the same fast gemm) and
//! the shifts (slices added back into the padded gradient), so no custom
//! backward is needed. The price is memory: autodiff keeps each layer's
//! stacked input (9x the layer's input) until the backward pass.
//!
//! The pass also stops after the deepest layer asked for (TCM needs
//! relu4_3 at most; ARF relu3_3), which the imported graph cannot.

use burn::nn::PaddingConfig2d;
use burn::nn::conv::Conv2d;
use burn::tensor::Tensor;
use burn::tensor::ops::PadMode;

use crate::vgg::VggLayer;
use crate::vgg::model::Model;

/// A 3x3 convolution with stride 1 and zero padding 1 (every VGG16
/// convolution): `x` `[n, c, h, w]`, `weight` `[o, c, 3, 3]`, `bias` `[o]`.
pub fn conv3x3(x: Tensor<4>, weight: Tensor<4>, bias: Option<Tensor<1>>) -> Tensor<4> {
    let [n, c, h, w] = x.dims();
    let [o, ci, kh, kw] = weight.dims();
    assert!(ci == c && kh == 3 && kw == 3, "conv3x3: input [{n}, {c}, {h}, {w}], weight [{o}, {ci}, {kh}, {kw}]");
    let padded = x.pad((1, 1, 1, 1), PadMode::Constant(0.0));
    // Column (c, ky, kx) of the weight matrix meets the input shifted by (ky, kx).
    let shifts: Vec<Tensor<4>> =
        (0..9).map(|k| padded.clone().slice([0..n, 0..c, k / 3..k / 3 + h, k % 3..k % 3 + w])).collect();
    let columns: Tensor<3> = Tensor::stack::<5>(shifts, 2).reshape([n, c * 9, h * w]);
    let matrix: Tensor<3> = weight.reshape([1, o, c * 9]);
    let matrix = if n > 1 { matrix.expand([n, o, c * 9]) } else { matrix };
    let out = matrix.matmul(columns);
    let out = match bias {
        Some(b) => out + b.reshape([1, o, 1]),
        None => out,
    };
    out.reshape([n, o, h, w])
}

/// Checks that a convolution is what `conv3x3` computes.
fn is_plain_3x3(conv: &Conv2d) -> bool {
    conv.kernel_size == [3, 3]
        && conv.stride == [1, 1]
        && conv.dilation == [1, 1]
        && conv.groups == 1
        && matches!(conv.padding, PaddingConfig2d::Explicit(1, 1, 1, 1))
}

/// The ReLU outputs of `model` up to the deepest of `layers`, in network
/// order (13 entries, `None` past the deepest), computed as the imported
/// graph computes them but with `conv3x3`.
pub fn forward(model: &Model, image: Tensor<4>, layers: &[VggLayer]) -> Vec<Option<Tensor<4>>> {
    let deepest = layers.iter().map(|l| l.index()).max().unwrap_or(0);
    let (scale, mean) = model.input_constants();
    let mut x = image.mul(scale.unsqueeze_dims(&[0, 1, 2])).sub(mean);
    let (convs, pools) = (model.convs(), model.pools());
    let mut out = vec![None; 13];
    for (i, conv) in convs.iter().enumerate().take(deepest + 1) {
        assert!(is_plain_3x3(conv), "VGG16 convolution {} is not a plain 3x3 convolution", i + 1);
        // A pool sits before the first convolution of stages 2 to 5.
        if let Some(p) = [2, 4, 7, 10].iter().position(|&first| first == i) {
            x = pools[p].forward(x);
        }
        let y = conv3x3(x, conv.weight.val(), conv.bias.as_ref().map(|b| b.val()));
        x = burn::tensor::activation::relu(y);
        out[i] = Some(x.clone());
    }
    out
}
