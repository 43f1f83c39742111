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
/// any machine. Each output chunk is written before it is read (see the
/// module's note on zeroed buffers).
pub fn sum_in_order(parts: &[&[f32]], len: usize) -> Vec<f32> {
    let mut out = Vec::new();
    sum_in_order_into(parts, len, &mut out);
    out
}

/// [`sum_in_order`] into `out` (resized to `len`), a buffer the caller keeps.
pub fn sum_in_order_into(parts: &[&[f32]], len: usize, out: &mut Vec<f32>) {
    const CHUNK: usize = 1 << 16;
    assert!(!parts.is_empty() && parts.iter().all(|p| p.len() == len), "parts of {len} values");
    out.clear();
    out.resize(len, 0.0);
    out.par_chunks_mut(CHUNK).enumerate().for_each(|(c, chunk)| {
        let range = c * CHUNK..c * CHUNK + chunk.len();
        chunk.copy_from_slice(&parts[0][range.clone()]);
        for part in &parts[1..] {
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
    }
}
