//! Feature-space correspondence: per-position descriptors from VGG feature
//! maps and exact nearest-neighbour search by cosine similarity (TCM's core,
//! also the semantic check of the VGG weights).

use burn::tensor::Tensor;
use burn::tensor::module::interpolate;
use burn::tensor::ops::{InterpolateMode, InterpolateOptions};

use crate::util::chunk_ranges;
use crate::util::tensor::to_vec;
use crate::vgg::{FeatureMaps, VggLayer};

/// Rows scaled to unit length (a zero row stays zero).
pub fn normalise_rows(x: Tensor<2>) -> Tensor<2> {
    let norm = x.clone().powf_scalar(2.0).sum_dim(1).sqrt().add_scalar(1e-8);
    x / norm
}

/// One feature block (e.g. relu3_1..relu3_3) of batch item `item` as a
/// matrix: the block's maps resized (nearest) to `size = [h, w]` and
/// concatenated along channels, `[h*w, sum C]` in row-major position order.
pub fn block_matrix(maps: &FeatureMaps, block: &[VggLayer], item: usize, size: [usize; 2]) -> Tensor<2> {
    let parts: Vec<Tensor<4>> = block
        .iter()
        .map(|&layer| {
            let map = maps.get(layer).clone().narrow(0, item, 1);
            let [_, _, h, w] = map.dims();
            if [h, w] == size {
                map
            } else {
                interpolate(map, InterpolateOptions::new(InterpolateMode::Nearest).with_output_size(size))
            }
        })
        .collect();
    let cat = Tensor::cat(parts, 1);
    let [_, c, h, w] = cat.dims();
    cat.reshape([c, h * w]).transpose()
}

/// The descriptor of one feature block: `block_matrix` with every row
/// L2-normalised. Two rows' dot product is the block's cosine similarity
/// (the released code normalises each concatenated block, not each layer).
pub fn block_descriptors(maps: &FeatureMaps, block: &[VggLayer], item: usize, size: [usize; 2]) -> Tensor<2> {
    normalise_rows(block_matrix(maps, block, item, size))
}

/// Several blocks' descriptors side by side (`[h*w, sum C]`): a dot product
/// is then the sum of the blocks' cosine similarities, as TCM sums relu3_x
/// and relu4_x.
pub fn multi_block_descriptors(maps: &FeatureMaps, blocks: &[&[VggLayer]], item: usize, size: [usize; 2]) -> Tensor<2> {
    Tensor::cat(blocks.iter().map(|b| block_descriptors(maps, b, item, size)).collect(), 1)
}

/// For every query row, the index of the key row with the largest dot product
/// (exact search; the query is processed `chunk` rows at a time so the
/// similarity matrix stays `chunk x keys`) and that similarity.
pub fn nearest_by_dot(query: Tensor<2>, keys: Tensor<2>, chunk: usize) -> (Vec<usize>, Vec<f32>) {
    let [nq, _] = query.dims();
    let keys_t = keys.transpose();
    let mut index = Vec::with_capacity(nq);
    let mut best = Vec::with_capacity(nq);
    for (start, len) in chunk_ranges(nq, chunk) {
        let sims = query.clone().narrow(0, start, len).matmul(keys_t.clone());
        let (value, arg) = sims.max_dim_with_indices(1);
        best.extend(to_vec(value));
        index.extend(
            arg.into_data()
                .convert::<i64>()
                .try_into_vec::<i64>()
                .expect("index tensor converts to i64")
                .into_iter()
                .map(|i| i as usize),
        );
    }
    (index, best)
}
