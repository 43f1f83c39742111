//! Float buffers reused across calls, and the in-order sum of per-part
//! buffers, for the plain-Rust passes that split their work into a fixed
//! number of parts (`field::host_fit`, `field::host_colour`, the VGG16
//! kernel's weights).
//!
//! Why: a buffer of tens of MB fresh from the system is mapped page by
//! page on first touch, and a zeroed one (`vec![0.0; n]`) read before it
//! is written (`+=`) is first mapped to the shared zero page and then
//! copied on write, with a TLB shootdown across the threads each time. On
//! fern's training step that was half of the step (`perf`); a kept buffer
//! costs one `memset`.

use std::sync::Mutex;

use rayon::prelude::*;

/// Up to `keep` spare buffers; a buffer given back replaces the smallest
/// kept one when all slots are full.
#[derive(Debug)]
pub struct BufferPool {
    spare: Mutex<Vec<Vec<f32>>>,
    keep: usize,
}

impl BufferPool {
    pub const fn new(keep: usize) -> Self {
        Self { spare: Mutex::new(Vec::new()), keep }
    }

    /// A buffer of `len` values whose contents are unspecified: the caller
    /// writes every value.
    pub fn take(&self, len: usize) -> Vec<f32> {
        let mut spare = self.spare.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        match spare.iter().position(|b| b.capacity() >= len) {
            Some(i) => {
                let mut buffer = spare.swap_remove(i);
                buffer.resize(len, 0.0);
                buffer.truncate(len);
                buffer
            }
            None => vec![0.0; len],
        }
    }

    /// A buffer of `len` zeros.
    pub fn zeroed(&self, len: usize) -> Vec<f32> {
        let mut buffer = self.take(len);
        buffer.fill(0.0);
        buffer
    }

    /// Keeps `buffer` for a later `take`.
    pub fn give_back(&self, buffer: Vec<f32>) {
        let mut spare = self.spare.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        if spare.len() < self.keep {
            spare.push(buffer);
        } else if let Some(smallest) = spare.iter_mut().min_by_key(|b| b.capacity())
            && smallest.capacity() < buffer.capacity()
        {
            *smallest = buffer;
        }
    }
}

/// The element-wise sum of `parts` (at least one, each `len` long), added
/// in part order whatever the threads, so the result is the same bits on
/// any machine.
pub fn sum_in_order(parts: &[&[f32]], len: usize) -> Vec<f32> {
    assert!(!parts.is_empty() && parts[0].len() == len, "parts of {len} values");
    let mut out = parts[0].to_vec();
    add_in_order(&mut out, &parts[1..]);
    out
}

/// Adds `rest` to `first` element-wise, in part order (in parallel over
/// chunks of elements, each element's additions in order): `first` ends
/// as [`sum_in_order`] of `first` and `rest`, the same bits, without an
/// output buffer and its copy of `first`.
pub fn add_in_order(first: &mut [f32], rest: &[&[f32]]) {
    const CHUNK: usize = 1 << 16;
    let len = first.len();
    assert!(rest.iter().all(|p| p.len() == len), "parts of {len} values");
    first.par_chunks_mut(CHUNK).enumerate().for_each(|(c, chunk)| {
        let range = c * CHUNK..c * CHUNK + chunk.len();
        for part in rest {
            chunk.iter_mut().zip(&part[range.clone()]).for_each(|(a, b)| *a += b);
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pool_hands_back_kept_buffers_zeroed_and_keeps_the_largest() {
        let pool = BufferPool::new(2);
        let mut a = pool.zeroed(10);
        a.fill(3.0);
        let ptr = a.as_ptr();
        pool.give_back(a);
        let b = pool.zeroed(8);
        assert_eq!((b.as_ptr(), b.len()), (ptr, 8), "the kept buffer is reused");
        assert!(b.iter().all(|v| *v == 0.0));
        pool.give_back(b);
        pool.give_back(vec![1.0; 4]);
        pool.give_back(vec![1.0; 100]);
        // Full: the 100-value buffer replaced the 4-value one.
        assert_eq!(pool.take(50).len(), 50);
        assert_eq!(pool.take(9).len(), 9);
    }

    #[test]
    fn parts_are_summed_in_order() {
        let len = (1 << 16) + 5;
        let a: Vec<f32> = (0..len).map(|i| i as f32 * 1e-3).collect();
        let b: Vec<f32> = (0..len).map(|i| 1e8 + (i % 7) as f32).collect();
        let c: Vec<f32> = b.iter().map(|v| -v).collect();
        let sum = sum_in_order(&[&a, &b, &c], len);
        for i in (0..len).step_by(997) {
            assert_eq!(sum[i], (a[i] + b[i]) + c[i], "{i}");
        }
        let mut in_place = a.clone();
        add_in_order(&mut in_place, &[&b, &c]);
        assert_eq!(in_place, sum, "adding into the first part gives the same bits");
    }
}
