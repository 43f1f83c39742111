//! Generic helpers every stage uses: the backend choice, tensor conversions,
//! the one `Image` type with PNG/GIF/npy I/O, atomic file writes that name the file
//! on failure, one run per output folder, progress events, per-step random generators, memory readings, host-device traffic counts, GPU launch and device-memory counts, per-part step timings, time and memory estimates from measured costs, reused buffers.

pub mod backend;
pub(crate) mod bin_fields;
pub mod config;
pub mod costs;
pub mod device_stats;
pub(crate) mod diverged;
pub mod files;
pub mod image;
pub mod input;
pub mod label;
pub mod lock;
pub mod memory;
pub mod metrics;
pub mod npy;
pub(crate) mod pool;
pub mod profile;
pub mod progress;
pub(crate) mod rng;
pub mod safetensors;
pub mod tensor;
pub mod tensor_file;
pub mod transfer;

/// `(start, len)` of consecutive pieces of at most `chunk` items covering
/// `0..total` (a `chunk` of 0 counts as 1).
pub fn chunk_ranges(total: usize, chunk: usize) -> impl Iterator<Item = (usize, usize)> {
    let chunk = chunk.max(1);
    (0..total).step_by(chunk).map(move |start| (start, chunk.min(total - start)))
}

/// `(start, len)` of consecutive pieces covering the items whose sizes
/// `sizes` lists, each of at most `chunk` items whose sizes sum to at most
/// `budget` (an item larger than `budget` is a piece of its own): rays cut
/// so that each piece's samples fit in one of a device's buffers.
pub fn budget_ranges(sizes: impl IntoIterator<Item = usize>, chunk: usize, budget: usize) -> Vec<(usize, usize)> {
    let chunk = chunk.max(1);
    let (mut ranges, mut start, mut len, mut sum) = (Vec::new(), 0, 0, 0usize);
    for size in sizes {
        if len > 0 && (len == chunk || sum.saturating_add(size) > budget) {
            ranges.push((start, len));
            (start, len, sum) = (start + len, 0, 0);
        }
        len += 1;
        sum = sum.saturating_add(size);
    }
    if len > 0 {
        ranges.push((start, len));
    }
    ranges
}

#[cfg(test)]
mod tests {
    #[test]
    fn budget_ranges_cut_by_count_and_by_size() {
        use super::budget_ranges;
        assert_eq!(budget_ranges([1; 10], 4, usize::MAX), super::chunk_ranges(10, 4).collect::<Vec<_>>());
        assert_eq!(budget_ranges([3, 3, 3, 9, 1, 1], 10, 6), vec![(0, 2), (2, 1), (3, 1), (4, 2)]);
        assert_eq!(budget_ranges([0usize; 0], 4, 6), vec![]);
        assert_eq!(budget_ranges([0, 0, 7], 4, 6), vec![(0, 2), (2, 1)]);
    }

    #[test]
    fn chunk_ranges_cover_everything_once() {
        let r: Vec<_> = super::chunk_ranges(10, 4).collect();
        assert_eq!(r, vec![(0, 4), (4, 4), (8, 2)]);
        assert_eq!(super::chunk_ranges(0, 4).count(), 0);
        assert_eq!(super::chunk_ranges(3, 0).count(), 3);
    }
}
