//! The stylization losses as small tensor functions (each tested against a
//! hand-computed value). Feature matrices are `[positions, channels]`.

use burn::tensor::Tensor;
use burn::tensor::module::avg_pool2d;
use burn::tensor::ops::AvgPoolOptions;

use crate::stylize::config::ColourNorm;
use crate::vgg::VggWeights;
use crate::vgg::features::{nearest_by_dot, normalise_rows};

/// Mean over rows of the cosine distance 1 - cos(a_i, b_i).
pub fn cosine_distance(a: Tensor<2>, b: Tensor<2>) -> Tensor<1> {
    let cos = (normalise_rows(a) * normalise_rows(b)).sum_dim(1);
    (-cos + 1.0).mean()
}

/// Mean of squared differences over all elements.
pub fn mse<const D: usize>(a: Tensor<D>, b: Tensor<D>) -> Tensor<1> {
    let d = a - b;
    (d.clone() * d).mean()
}

/// Oxford's VGG16 takes Caffe-convention input (x*255 - mean), the released
/// code's torchvision weights ((x - mean) / std, std about 0.226): the same
/// image enters about 255 x 0.226 = 57.6 times larger with Oxford's, and so
/// do the ReLU features (nearly positively homogeneous). Feature MSEs are
/// measured in torchvision's units, so λ' keeps the paper's meaning.
pub const FEATURE_UNIT: f32 = 57.6;

/// The size of one torchvision feature unit in the features of `weights`.
pub fn feature_unit(weights: VggWeights) -> f32 {
    match weights {
        VggWeights::Oxford => FEATURE_UNIT,
        VggWeights::Torchvision => 1.0,
    }
}

/// The content term: mean squared difference of two feature matrices of
/// VGG16 with `weights`, in torchvision feature units.
pub fn content_loss(render: Tensor<2>, content: Tensor<2>, weights: VggWeights) -> Tensor<1> {
    let unit = feature_unit(weights);
    mse(render, content) / (unit * unit)
}

/// `[1, 3, H, W]` -> `[1, 3, H/2, W/2]`, each pixel the mean of a 2x2
/// block: a 0.5x bilinear resize (without align_corners) computes exactly this.
pub fn half(image: Tensor<4>) -> Tensor<4> {
    avg_pool2d(image, AvgPoolOptions::new([2, 2]).with_stride([2, 2]))
}

/// Mean colour of each `patch` x `patch` block of an image `[1, 3, H, W]`,
/// as `[(H/patch) * (W/patch), 3]` in row-major patch order (trailing pixels
/// beyond a multiple of `patch` are left out, as VGG's relu5 grid does).
pub fn patch_means(image: Tensor<4>, patch: usize) -> Tensor<2> {
    let pooled = avg_pool2d(image, AvgPoolOptions::new([patch, patch]).with_stride([patch, patch]));
    let [_, c, h, w] = pooled.dims();
    pooled.reshape([c, h * w]).transpose()
}

/// Paper eq. 9: squared colour distance between rendered patch means and
/// their matched reference patch colours at the positions whose `mask`
/// (`[positions, 1]`) is 1 (unmatched and background positions carry 0):
/// summed over channels and averaged over the masked positions
/// (`Matched`), or averaged over channels and all positions (`AllPositions`).
pub fn colour_loss(patches: Tensor<2>, targets: Tensor<2>, mask: Tensor<2>, norm: ColourNorm) -> Tensor<1> {
    let [n, c] = patches.dims();
    let d = patches - targets;
    let masked = ((d.clone() * d).sum_dim(1) * mask.clone()).sum();
    match norm {
        ColourNorm::Matched => masked / mask.sum().clamp_min(1.0),
        ColourNorm::AllPositions => masked / (n * c).max(1) as f32,
    }
}

/// `[positions, 1]`: 1 where a patch's channel mean is at most `white`, 0
/// where it is brighter (background, for L_color's mask).
pub fn not_white(patches: Tensor<2>, white: f32) -> Tensor<2> {
    patches.mean_dim(1).lower_equal_elem(white).float()
}

/// Image total variation: mean squared difference of horizontal neighbours
/// plus that of vertical neighbours, for `[1, 3, H, W]`.
pub fn image_tv(image: Tensor<4>) -> Tensor<1> {
    let [_, _, h, w] = image.dims();
    let dx = image.clone().narrow(3, 1, w - 1) - image.clone().narrow(3, 0, w - 1);
    let dy = image.clone().narrow(2, 1, h - 1) - image.narrow(2, 0, h - 1);
    (dx.clone() * dx).mean() + (dy.clone() * dy).mean()
}

/// ARF's nearest-neighbour feature matching: every render position is pulled
/// towards its nearest style position by cosine (searched afresh on the
/// current features, without gradient, chunked), loss = mean cosine distance.
pub fn nnfm_loss(render: Tensor<2>, style: Tensor<2>, chunk: usize) -> Tensor<1> {
    let query = normalise_rows(render.clone().detach());
    let keys = normalise_rows(style.clone());
    let (idx, _) = nearest_by_dot(query.inner(), keys.inner(), chunk);
    let idx = crate::util::tensor::indices(idx.into_iter().map(|i| i as i32).collect(), &style.device());
    cosine_distance(render, crate::util::tensor::select_rows(style, idx))
}
