//! The grid being stylized: SH degree 0, density frozen, its RMSprop state
//! and SH total variation; and the chunked gradient of a loss over rendered
//! rays (the second half of deferred back-propagation).

use burn::tensor::{IndexingUpdateOp, Tensor};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use crate::field::frozen::{self, FrozenSamples};
use crate::field::grid::RadianceGrid;
use crate::field::optim::{Rmsprop, RowSubset, TvNorm, total_variation};
use crate::util::chunk_ranges;
use crate::util::tensor::{assign_rows, indices, select_rows};

/// The grid being stylized: SH degree 0, density frozen, RMSprop state.
pub struct StyleField {
    pub grid: RadianceGrid,
    rms: Tensor<2>,
    /// Per row, its +x / +y / +z neighbour row (itself when empty): SH TV.
    neighbours: [Vec<i32>; 3],
}

impl StyleField {
    /// Cuts a photoreal grid to view-independent colour (the DC band).
    pub fn new(mut grid: RadianceGrid) -> Self {
        grid.truncate_sh(0);
        let rows = grid.num_rows();
        let neighbours = std::array::from_fn(|axis| {
            (0..rows).map(|row| grid.neighbour_row(row, axis).unwrap_or(row as i32)).collect()
        });
        let rms = Tensor::zeros([rows, 3], &grid.device());
        Self { grid, rms, neighbours }
    }

    pub fn reset_optimiser(&mut self) {
        self.rms = Tensor::zeros([self.grid.num_rows(), 3], &self.grid.device());
    }

    /// Dense RMSprop step on the SH rows (density untouched).
    pub fn rmsprop(&mut self, grad: Tensor<2>, lr: f32, beta: f32, eps: f32) {
        Rmsprop { beta, eps }.step_dense(&mut self.grid.sh, &mut self.rms, grad, lr);
    }

    /// `into` plus the gradient of `weight` x the SH total variation over a
    /// random `fraction` of the rows (mean over those rows of sqrt(sum of
    /// squared differences to the +x/+y/+z neighbours)). Adding into the
    /// caller's gradient saves a grid-sized buffer and a grid-sized sum per step.
    pub fn add_tv_gradient(&self, into: Tensor<2>, weight: f32, fraction: f32, rng: &mut ChaCha8Rng) -> Tensor<2> {
        let n = self.grid.num_rows();
        if weight <= 0.0 || n == 0 {
            return into;
        }
        let count = ((n as f32 * fraction).ceil() as usize).clamp(1, n);
        let core: Vec<i32> = (0..count).map(|_| rng.random_range(0..n) as i32).collect();
        // Leaf = the rows involved (the picked rows and their neighbours), local indices.
        let lists: Vec<Vec<i32>> = std::iter::once(core.clone())
            .chain(self.neighbours.iter().map(|nb| core.iter().map(|&r| nb[r as usize]).collect()))
            .collect();
        let subset = RowSubset::of(n, &lists.concat());
        let device = self.grid.device();
        let rows = indices(subset.rows().to_vec(), &device);
        let leaf = select_rows(self.grid.sh.clone(), rows.clone()).autodiff().require_grad();
        let mut gathered = lists
            .into_iter()
            .map(|l| select_rows(leaf.clone(), indices(l.iter().map(|&r| subset.local(r)).collect(), &device)));
        let centre = gathered.next().expect("the picked rows");
        let tv = total_variation(centre, gathered, TvNorm::PerVoxel) * (weight / count as f32);
        match leaf.grad(&tv.backward()) {
            Some(g) => assign_rows(into, rows, g, IndexingUpdateOp::Add),
            None => into,
        }
    }
}

/// d/d(sh) of the sum over ray chunks of `loss_of(rendered chunk, first ray, rays)`:
/// each chunk is rendered with autodiff and back-propagated on its own, so
/// memory is bounded by the chunk (the second half of deferred back-propagation).
/// The autodiff leaf of a chunk is only the rows its samples touch (a grid
/// has millions of rows, a chunk touches a few percent of them); their
/// gradients are added into one full-size buffer.
pub fn chunked_gradient(
    sh: &Tensor<2>,
    samples: &FrozenSamples,
    background: [f32; 3],
    chunk: usize,
    loss_of: &dyn Fn(Tensor<2>, usize, usize) -> Tensor<1>,
) -> Tensor<2> {
    let device = sh.device();
    let mut total = Tensor::zeros(sh.dims(), &device);
    let mut subset = RowSubset::default();
    for (start, len) in chunk_ranges(samples.num_rays, chunk) {
        let mut part = samples.range(start, len);
        subset.reset_to(sh.dims()[0], &part.corner_rows);
        for r in part.corner_rows.iter_mut() {
            *r = subset.local(*r);
        }
        let ft = part.upload(&device);
        let rows = indices(subset.rows().to_vec(), &device);
        let leaf = select_rows(sh.clone(), rows.clone()).autodiff().require_grad();
        let rgb = frozen::render_colour(leaf.clone(), &ft, background);
        let loss = loss_of(rgb, start, len);
        // A chunk whose rays all miss the scene renders the background: no graph, no gradient.
        if loss.is_tracked()
            && let Some(g) = leaf.grad(&loss.backward())
        {
            total = assign_rows(total, rows, g, IndexingUpdateOp::Add);
        }
    }
    total
}
