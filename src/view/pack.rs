//! A field packed for a WebGL2 page: the sparse lattice as bricks of 4³
//! lattice points in a 3D texture atlas, found through an index texture of
//! one entry per brick.
//!
//! Bytes per occupied brick point: 4 (density, f32, exact) + 8 per four SH
//! coefficients (f16: 2 bytes for SH degree 0's three, 56 for degree 2's
//! 27, as RGBA16F texels). An f16 coefficient is off by at most 1/2048 of
//! its size, far below what an 8-bit screenshot resolves; density stays f32
//! because transmittance compounds its error along the ray. The index also
//! says which bricks the page may skip whole: those whose 5³ closure (the
//! brick and the lattice points its cells reach in the next bricks) has no
//! point of positive density, the condition refnpr's own march skips dead
//! blocks on when it renders a checkpoint, so no sample that could count is
//! skipped.

use serde::{Deserialize, Serialize};

use crate::field::checkpoint::Checkpoint;
use crate::field::grid::{GridGeometry, RadianceGrid};
use crate::field::march::{ColourCorners, MarchParams};
use crate::scene::camera::NdcParams;
use crate::scene::sh;
use anyhow::Result;

/// Lattice points along a brick's side. 4, not 8: bricks of 4³ hold a
/// thin surface with less empty space around it (lego's atlas is 55 % full
/// at 8³) and let rays skip empty space in finer steps.
pub const BRICK: usize = 4;
/// Bricks along each side of the atlas at most: 64 x 4 = 256 texels, the
/// 3D texture size every WebGL2 implementation supports.
const ATLAS_BRICKS: usize = 64;
/// A density no fitted field has: marks a brick's inactive lattice points
/// (they count as zero density and carry no colour, as in the march).
pub const INACTIVE: f32 = -3.0e38;
/// Index entries: a brick's atlas slot (>= 0), or one of these, or
/// `-(slot + 3)` for a brick whose data neighbouring cells read but whose
/// own cells a ray may skip (`skip_entry`).
pub const EMPTY_NEAR_MATTER: i32 = -1;
pub const EMPTY_SKIP: i32 = -2;

/// The entry of a brick at `slot` that rays skip.
pub fn skip_entry(slot: usize) -> i32 {
    -(slot as i32) - 3
}

/// What the page needs to know about a packed field (`field.json`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FieldHeader {
    pub geometry: GridGeometry,
    pub sh_degree: u32,
    pub ndc: Option<NdcParams>,
    pub background: [f32; 3],
    /// Step (lattice units), density threshold, stop threshold.
    pub step: f32,
    pub sigma_threshold: f32,
    pub stop_threshold: f32,
    /// Colour interpolation over active corners only (refnpr's default).
    pub renormalised_colour: bool,
    /// Lattice points along a brick's side.
    pub brick: usize,
    /// Bricks along x, y, z of the lattice (the index texture's size).
    pub blocks: [usize; 3],
    /// Bricks along x, y, z of the atlas (its texture size / `brick`).
    pub atlas: [usize; 3],
    pub slots: usize,
    /// RGBA16F textures of SH coefficients (coefficient j: texture j / 4,
    /// channel j % 4; j = channel * basis + basis function, refnpr's row).
    pub sh_textures: usize,
    /// The checkpoint's step and fingerprint (which field this is).
    pub checkpoint_step: usize,
    pub fingerprint: String,
    /// Byte lengths of the three parts of `field.bin`, in order.
    pub index_bytes: usize,
    pub density_bytes: usize,
    pub sh_bytes: usize,
    /// The far background's `[width, height]` (`field::environment`), when
    /// the field has one; its RGB (f32) follows the SH in `field.bin`.
    #[serde(default)]
    pub far: Option<[usize; 2]>,
    #[serde(default)]
    pub far_bytes: usize,
}

/// A packed field: the page's header and the textures it describes.
pub struct PackedField {
    pub header: FieldHeader,
    pub lattice: Lattice,
    /// The far background's interleaved RGB (empty without one).
    pub far: Vec<f32>,
}

impl PackedField {
    /// `field.bin`: the header's length (u32), its JSON, zero padding to a
    /// multiple of 4, then the index (i32), the density (f32) and the SH
    /// (f16 bits), then the far background's RGB (f32) when there is one,
    /// all little-endian, x fastest in every texture; written
    /// once into one buffer (fern's is 0.4 GB).
    pub fn to_file(&self) -> Result<Vec<u8>> {
        let h = &self.header;
        let json = serde_json::to_vec(h)?;
        let start = (4 + json.len()).next_multiple_of(4);
        let mut out = Vec::with_capacity(start + h.index_bytes + h.density_bytes + h.sh_bytes);
        out.extend_from_slice(&(json.len() as u32).to_le_bytes());
        out.extend_from_slice(&json);
        out.resize(start, 0);
        let l = &self.lattice;
        l.index.iter().for_each(|v| out.extend_from_slice(&v.to_le_bytes()));
        l.density.iter().for_each(|v| out.extend_from_slice(&v.to_le_bytes()));
        l.sh_bits.iter().for_each(|v| out.extend_from_slice(&v.to_le_bytes()));
        self.far.iter().for_each(|v| out.extend_from_slice(&v.to_le_bytes()));
        Ok(out)
    }
}

/// The lattice as the page's textures.
pub struct Lattice {
    /// Bricks along x, y, z of the lattice and one index entry per brick.
    pub blocks: [usize; 3],
    pub index: Vec<i32>,
    /// Bricks along x, y, z of the atlas, and the bricks stored.
    pub atlas: [usize; 3],
    pub slots: usize,
    /// One density per atlas texel (`INACTIVE` where no point is).
    pub density: Vec<f32>,
    /// `sh_textures` RGBA textures of f16 bits, one after the other.
    pub sh_bits: Vec<u16>,
    pub sh_textures: usize,
}

/// Packs `ck`'s field (refused when it needs a bigger atlas than WebGL2
/// guarantees).
pub fn pack(ck: &Checkpoint) -> Result<PackedField> {
    let lattice = pack_lattice(&ck.grid)?;
    let MarchParams { step, sigma_threshold, stop_threshold, colour_corners, .. } = ck.meta.render.march;
    let header = FieldHeader {
        geometry: ck.grid.geometry,
        sh_degree: ck.grid.sh_degree,
        ndc: ck.meta.ndc,
        background: ck.meta.background,
        step,
        sigma_threshold,
        stop_threshold,
        renormalised_colour: colour_corners == ColourCorners::Renormalised,
        brick: BRICK,
        blocks: lattice.blocks,
        atlas: lattice.atlas,
        slots: lattice.slots,
        sh_textures: lattice.sh_textures,
        checkpoint_step: ck.meta.step,
        fingerprint: format!("{:016x}", ck.fingerprint()),
        index_bytes: lattice.index.len() * 4,
        density_bytes: lattice.density.len() * 4,
        sh_bytes: lattice.sh_bits.len() * 2,
        far: ck.grid.far.as_ref().map(|f| [f.width, f.height]),
        far_bytes: ck.grid.far.as_ref().map_or(0, |f| f.rgb.len() * 4),
    };
    let far = ck.grid.far.as_ref().map(|f| f.rgb.clone()).unwrap_or_default();
    Ok(PackedField { header, lattice, far })
}

/// The index and the atlas of `grid`.
pub fn pack_lattice(grid: &RadianceGrid) -> Result<Lattice> {
    let geo = grid.geometry;
    let blocks = geo.res.map(|r| r.div_ceil(BRICK));
    let block_of = |b: [usize; 3]| (b[2] * blocks[1] + b[1]) * blocks[0] + b[0];
    let nblocks = blocks.iter().product::<usize>();
    // Bricks with an active point, and with a point of positive density: a
    // sample whose cell's closure has none has density <= 0 and is dropped
    // (the density is frozen in a view, as in refnpr's checkpoint renders).
    let (mut occupied, mut alive) = (vec![false; nblocks], vec![false; nblocks]);
    for (flat, &row) in grid.links.iter().enumerate() {
        if row >= 0 {
            let b = block_of(geo.unflat(flat).map(|v| v / BRICK));
            occupied[b] = true;
            alive[b] |= grid.density_cpu[row as usize] > 0.0;
        }
    }
    let mut index = vec![EMPTY_SKIP; nblocks];
    let mut slots = Vec::new(); // slot -> block coordinates
    for bz in 0..blocks[2] {
        for by in 0..blocks[1] {
            for bx in 0..blocks[0] {
                let b = [bx, by, bz];
                let f = block_of(b);
                let reached = closure_any(&alive, blocks, b, block_of);
                if occupied[f] {
                    index[f] = if reached { slots.len() as i32 } else { skip_entry(slots.len()) };
                    slots.push(b);
                } else if reached {
                    index[f] = EMPTY_NEAR_MATTER;
                }
            }
        }
    }
    let atlas = atlas_size(slots.len())?;
    let (density, sh_bits, sh_textures) = fill_atlas(grid, &slots, atlas);
    Ok(Lattice { blocks, index, atlas, slots: slots.len(), density, sh_bits, sh_textures })
}

/// Whether brick `b` or a brick after it along any axes (the lattice points
/// its cells reach) is flagged in `flags`.
fn closure_any(flags: &[bool], blocks: [usize; 3], b: [usize; 3], block_of: impl Fn([usize; 3]) -> usize) -> bool {
    (0..8).any(|o: usize| {
        let n = [b[0] + (o >> 2 & 1), b[1] + (o >> 1 & 1), b[2] + (o & 1)];
        (0..3).all(|a| n[a] < blocks[a]) && flags[block_of(n)]
    })
}

/// The atlas's bricks per side for `slots` bricks: the smallest box of
/// at most `ATLAS_BRICKS` per side that holds them (a box of whole slabs
/// wastes up to a slab).
fn atlas_size(slots: usize) -> Result<[usize; 3]> {
    let mut best: Option<[usize; 3]> = None;
    for ax in 1..=ATLAS_BRICKS {
        for ay in 1..=ATLAS_BRICKS {
            let az = slots.div_ceil(ax * ay).max(1);
            let volume = |a: [usize; 3]| a[0] * a[1] * a[2];
            if az <= ATLAS_BRICKS && best.is_none_or(|b| volume([ax, ay, az]) < volume(b)) {
                best = Some([ax, ay, az]);
            }
        }
    }
    best.ok_or_else(|| {
        anyhow::anyhow!(
            "the field has {slots} occupied {BRICK}³ bricks; the viewer holds at most {} (a 256³ texture atlas): \
             prune the field or fit a coarser lattice",
            ATLAS_BRICKS.pow(3)
        )
    })
}

/// The atlas textures: density (INACTIVE at empty points) and the SH
/// coefficients as f16 bits, RGBA per texel, `textures` of them.
fn fill_atlas(grid: &RadianceGrid, slots: &[[usize; 3]], atlas: [usize; 3]) -> (Vec<f32>, Vec<u16>, usize) {
    let geo = grid.geometry;
    let stride = 3 * sh::num_basis(grid.sh_degree);
    let textures = stride.div_ceil(4);
    let size = atlas.map(|a| a * BRICK);
    let texels = size.iter().product::<usize>();
    let mut density = vec![INACTIVE; texels];
    let mut sh_bits = vec![0u16; textures * texels * 4];
    let sh_rows = grid.sh_cpu();
    for (slot, b) in slots.iter().enumerate() {
        let origin = [slot % atlas[0], (slot / atlas[0]) % atlas[1], slot / (atlas[0] * atlas[1])].map(|s| s * BRICK);
        for k in 0..BRICK {
            for j in 0..BRICK {
                for i in 0..BRICK {
                    let p = [b[0] * BRICK + i, b[1] * BRICK + j, b[2] * BRICK + k];
                    if (0..3).any(|a| p[a] >= geo.res[a]) {
                        continue;
                    }
                    let row = grid.links[geo.flat(p[0], p[1], p[2])];
                    if row < 0 {
                        continue;
                    }
                    let t = ((origin[2] + k) * size[1] + origin[1] + j) * size[0] + origin[0] + i;
                    density[t] = grid.density_cpu[row as usize];
                    let coefficients = &sh_rows[row as usize * stride..(row as usize + 1) * stride];
                    for (c, &v) in coefficients.iter().enumerate() {
                        sh_bits[((c / 4) * texels + t) * 4 + c % 4] = half::f16::from_f32(v).to_bits();
                    }
                }
            }
        }
    }
    (density, sh_bits, textures)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::grid::sphere_grid;

    /// Every lattice point is found through the index where the page looks
    /// for it, with its density to the bit and its SH to f16's precision;
    /// every brick rays skip has no point of positive density within reach.
    #[test]
    fn every_point_is_where_the_page_reads_it_and_skips_miss_nothing() {
        let grid = sphere_grid(20, &Default::default());
        let lattice = pack_lattice(&grid).unwrap();
        let geo = grid.geometry;
        let size = lattice.atlas.map(|a| a * BRICK);
        let texels = size.iter().product::<usize>();
        let stride = 3 * sh::num_basis(grid.sh_degree);
        let sh_rows = grid.sh_cpu();
        let entry = |p: [usize; 3]| {
            let b = p.map(|v| v / BRICK);
            lattice.index[(b[2] * lattice.blocks[1] + b[1]) * lattice.blocks[0] + b[0]]
        };
        let (mut active, mut skipped_alive) = (0, 0);
        for flat in 0..grid.links.len() {
            let p = geo.unflat(flat);
            let row = grid.links[flat];
            let e = entry(p);
            let slot = if e >= 0 {
                Some(e as usize)
            } else if e <= -3 {
                Some((-e - 3) as usize)
            } else {
                None
            };
            let Some(slot) = slot else {
                assert!(row < 0, "an active point in a brick without data at {p:?}");
                continue;
            };
            let a = lattice.atlas;
            let origin = [slot % a[0], (slot / a[0]) % a[1], slot / (a[0] * a[1])].map(|v| v * BRICK);
            let t =
                ((origin[2] + p[2] % BRICK) * size[1] + origin[1] + p[1] % BRICK) * size[0] + origin[0] + p[0] % BRICK;
            if row < 0 {
                assert_eq!(lattice.density[t], INACTIVE);
                continue;
            }
            active += 1;
            let row = row as usize;
            assert_eq!(lattice.density[t].to_bits(), grid.density_cpu[row].to_bits());
            for c in 0..stride {
                let bits = lattice.sh_bits[((c / 4) * texels + t) * 4 + c % 4];
                let v = sh_rows[row * stride + c];
                assert!((half::f16::from_bits(bits).to_f32() - v).abs() <= v.abs() / 1024.0 + 1e-7);
            }
        }
        assert_eq!(active, grid.num_rows());
        // A brick rays skip: no positive density at any point its cells
        // reach (the brick's 5³ closure).
        let [bx, by, bz] = lattice.blocks;
        let mut skipped_bricks = 0;
        for b in (0..bx * by * bz).map(|f| [f % bx, (f / bx) % by, f / (bx * by)]) {
            let e = entry(b.map(|v| v * BRICK));
            if e != EMPTY_SKIP && e > -3 {
                continue;
            }
            skipped_bricks += 1;
            let side = BRICK + 1;
            for o in 0..side.pow(3) {
                let q = [b[0] * BRICK + o % side, b[1] * BRICK + (o / side) % side, b[2] * BRICK + o / (side * side)];
                if (0..3).all(|a| q[a] < geo.res[a]) {
                    let row = grid.links[geo.flat(q[0], q[1], q[2])];
                    skipped_alive += usize::from(row >= 0 && grid.density_cpu[row as usize] > 0.0);
                }
            }
        }
        assert!(skipped_bricks > 0, "the ball's corners are skipped");
        assert_eq!(skipped_alive, 0, "a brick rays skip holds a point of positive density");
    }
}
