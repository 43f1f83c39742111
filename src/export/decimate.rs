//! Fewer triangles for the same surface: quadric-error edge collapse
//! (Garland and Heckbert, 1997), written from the paper.
//!
//! Every vertex carries the sum of the squared distances to the planes of
//! its triangles (a 4x4 quadric, area-weighted); collapsing an edge merges
//! the two quadrics and places the vertex where their sum is least. The
//! cheapest edge goes first. A collapse is refused when it would change the
//! surface's topology (the link condition: the two ends share exactly the
//! two neighbours across the edge, so a closed surface stays closed and
//! manifold) or fold a triangle over (its normal turning by more than a
//! right angle). Vertices on an open border (a forward-facing field's
//! frustum edge) keep their place, so the border keeps its outline. Colours
//! follow the vertex along the edge.

use std::cmp::Ordering;
use std::collections::BinaryHeap;

use glam::{DMat3, DVec3};

use crate::export::mesh::{Mesh, edge_uses, set_normals};

/// The surface of `mesh` with at most `target` triangles (fewer only when a
/// further collapse would break the surface's topology or fold it); the
/// mesh itself when it has no more than `target`.
pub fn decimate(mesh: &Mesh, target: usize) -> Mesh {
    if mesh.triangles.len() <= target {
        return mesh.clone();
    }
    let mut state = Collapser::new(mesh);
    let mut heap = BinaryHeap::new();
    for &(a, b) in edge_uses(&mesh.triangles).keys() {
        if let Some(c) = state.candidate(a, b) {
            heap.push(c);
        }
    }
    // Sorting the map's edges is not needed for determinism: ties in cost
    // are broken by the vertex numbers (Candidate's order).
    let mut alive = mesh.triangles.len();
    while alive > target.max(4) {
        let Some(c) = heap.pop() else { break };
        if !state.is_current(&c) || !state.topology_kept(c.keep, c.remove) || state.folds(c.keep, c.remove, c.at) {
            continue;
        }
        alive -= state.collapse(c.keep, c.remove, c.at);
        for w in state.neighbours(c.keep) {
            if let Some(next) = state.candidate(c.keep, w) {
                heap.push(next);
            }
        }
    }
    state.into_mesh()
}

/// A symmetric 4x4 quadric (its upper triangle, row by row): the weighted
/// sum of squared distances to a set of planes.
#[derive(Debug, Clone, Copy, Default)]
struct Quadric([f64; 10]);

impl Quadric {
    /// `weight` times the squared distance to the plane `n . p + d = 0`.
    fn of_plane(n: DVec3, d: f64, weight: f64) -> Self {
        let [a, b, c] = n.to_array();
        Quadric([a * a, a * b, a * c, a * d, b * b, b * c, b * d, c * c, c * d, d * d].map(|x| x * weight))
    }

    fn add(&mut self, other: &Quadric) {
        for (s, o) in self.0.iter_mut().zip(other.0) {
            *s += o;
        }
    }

    fn error(&self, p: DVec3) -> f64 {
        let q = &self.0;
        let (x, y, z) = (p.x, p.y, p.z);
        q[0] * x * x
            + q[4] * y * y
            + q[7] * z * z
            + 2.0 * (q[1] * x * y + q[2] * x * z + q[5] * y * z)
            + 2.0 * (q[3] * x + q[6] * y + q[8] * z)
            + q[9]
    }

    /// The point of least error, when the planes pin one down (not on a flat
    /// or a straight crease, where every point of a line or plane is as good).
    fn minimiser(&self) -> Option<DVec3> {
        let q = &self.0;
        let m =
            DMat3::from_cols(DVec3::new(q[0], q[1], q[2]), DVec3::new(q[1], q[4], q[5]), DVec3::new(q[2], q[5], q[7]));
        let scale = (q[0] + q[4] + q[7]) / 3.0;
        if scale <= 0.0 || m.determinant().abs() < 1e-6 * scale.powi(3) {
            return None;
        }
        Some(m.inverse() * -DVec3::new(q[3], q[6], q[8]))
    }
}

/// One possible collapse: `remove` merges into `keep`, which moves to `at`.
#[derive(Debug, Clone, Copy)]
struct Candidate {
    cost: f64,
    keep: u32,
    remove: u32,
    at: DVec3,
    /// The two ends' versions when the cost was computed.
    versions: (u32, u32),
}

impl PartialEq for Candidate {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}
impl Eq for Candidate {}
impl PartialOrd for Candidate {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Candidate {
    /// Reversed, so the max-heap pops the cheapest first.
    fn cmp(&self, other: &Self) -> Ordering {
        other.cost.total_cmp(&self.cost).then((other.keep, other.remove).cmp(&(self.keep, self.remove)))
    }
}

/// The mesh being simplified: triangles stay in place (dead ones flagged),
/// every vertex lists the triangles it is in.
struct Collapser {
    positions: Vec<DVec3>,
    colours: Vec<[f32; 3]>,
    quadrics: Vec<Quadric>,
    /// On an open border: never moves.
    border: Vec<bool>,
    /// Bumped by every change to the vertex, invalidating queued candidates.
    version: Vec<u32>,
    removed: Vec<bool>,
    triangles: Vec<[u32; 3]>,
    dead: Vec<bool>,
    triangles_of: Vec<Vec<u32>>,
}

impl Collapser {
    fn new(mesh: &Mesh) -> Self {
        let n = mesh.positions.len();
        let positions: Vec<DVec3> = mesh.positions.iter().map(|p| p.as_dvec3()).collect();
        let mut quadrics = vec![Quadric::default(); n];
        let mut triangles_of = vec![Vec::new(); n];
        for (f, t) in mesh.triangles.iter().enumerate() {
            let [a, b, c] = t.map(|v| positions[v as usize]);
            let cross = (b - a).cross(c - a);
            let area = 0.5 * cross.length();
            if area > 0.0 {
                let normal = cross.normalize();
                let q = Quadric::of_plane(normal, -normal.dot(a), area);
                t.iter().for_each(|&v| quadrics[v as usize].add(&q));
            }
            t.iter().for_each(|&v| triangles_of[v as usize].push(f as u32));
        }
        let mut border = vec![false; n];
        for (&(a, b), &uses) in &edge_uses(&mesh.triangles) {
            if uses != 2 {
                border[a as usize] = true;
                border[b as usize] = true;
            }
        }
        Self {
            positions,
            colours: mesh.colours.clone(),
            quadrics,
            border,
            version: vec![0; n],
            removed: vec![false; n],
            triangles: mesh.triangles.clone(),
            dead: vec![false; mesh.triangles.len()],
            triangles_of,
        }
    }

    /// The vertices sharing a live triangle with `v`, sorted.
    fn neighbours(&self, v: u32) -> Vec<u32> {
        let mut out: Vec<u32> = self.triangles_of[v as usize]
            .iter()
            .filter(|&&f| !self.dead[f as usize])
            .flat_map(|&f| self.triangles[f as usize])
            .filter(|&w| w != v)
            .collect();
        out.sort_unstable();
        out.dedup();
        out
    }

    /// The collapse of edge `a`-`b` and its cost (None when both ends lie on
    /// a border). A border end stays where it is; otherwise the vertex goes
    /// to the quadric's least point when that lies near the edge, else to
    /// the better of the two ends and the midpoint.
    fn candidate(&self, a: u32, b: u32) -> Option<Candidate> {
        let (pa, pb) = (self.positions[a as usize], self.positions[b as usize]);
        let mut q = self.quadrics[a as usize];
        q.add(&self.quadrics[b as usize]);
        let (keep, remove, at) = match (self.border[a as usize], self.border[b as usize]) {
            (true, true) => return None,
            (true, false) => (a, b, pa),
            (false, true) => (b, a, pb),
            (false, false) => {
                let mid = 0.5 * (pa + pb);
                let near = |p: &DVec3| p.distance(mid) <= pa.distance(pb);
                let best = q.minimiser().filter(near).unwrap_or_else(|| {
                    [pa, pb, mid].into_iter().min_by(|x, y| q.error(*x).total_cmp(&q.error(*y))).unwrap_or(mid)
                });
                (a, b, best)
            }
        };
        let versions = (self.version[keep as usize], self.version[remove as usize]);
        Some(Candidate { cost: q.error(at).max(0.0), keep, remove, at, versions })
    }

    fn is_current(&self, c: &Candidate) -> bool {
        !self.removed[c.keep as usize]
            && !self.removed[c.remove as usize]
            && (self.version[c.keep as usize], self.version[c.remove as usize]) == c.versions
    }

    /// The link condition: the edge lies between exactly two triangles and
    /// its ends share no neighbour but the two across it.
    fn topology_kept(&self, keep: u32, remove: u32) -> bool {
        let across: Vec<u32> = self
            .shared_triangles(keep, remove)
            .map(|f| self.triangles[f as usize].into_iter().find(|&w| w != keep && w != remove).unwrap_or(keep))
            .collect();
        if across.len() != 2 || across[0] == across[1] {
            return false;
        }
        let (nk, nr) = (self.neighbours(keep), self.neighbours(remove));
        let common = nk.iter().filter(|w| nr.binary_search(w).is_ok()).count();
        common == 2
    }

    fn shared_triangles(&self, keep: u32, remove: u32) -> impl Iterator<Item = u32> + '_ {
        self.triangles_of[keep as usize]
            .iter()
            .copied()
            .filter(move |&f| !self.dead[f as usize] && self.triangles[f as usize].contains(&remove))
    }

    /// Whether moving both ends to `at` turns a remaining triangle's normal
    /// by more than a right angle or flattens it to nothing.
    fn folds(&self, keep: u32, remove: u32, at: DVec3) -> bool {
        [keep, remove].iter().flat_map(|&v| self.triangles_of[v as usize].iter()).any(|&f| {
            let t = self.triangles[f as usize];
            if self.dead[f as usize] || (t.contains(&keep) && t.contains(&remove)) {
                return false;
            }
            let before = t.map(|v| self.positions[v as usize]);
            let after = t.map(|v| if v == keep || v == remove { at } else { self.positions[v as usize] });
            let normal = |[a, b, c]: [DVec3; 3]| (b - a).cross(c - a);
            let (n0, n1) = (normal(before), normal(after));
            n1.length_squared() == 0.0 || n0.dot(n1) < 0.0
        })
    }

    /// Merges `remove` into `keep` at `at`; returns the triangles removed.
    fn collapse(&mut self, keep: u32, remove: u32, at: DVec3) -> usize {
        let shared: Vec<u32> = self.shared_triangles(keep, remove).collect();
        for &f in &shared {
            self.dead[f as usize] = true;
        }
        let moved = std::mem::take(&mut self.triangles_of[remove as usize]);
        for f in moved {
            if !self.dead[f as usize] {
                for v in &mut self.triangles[f as usize] {
                    if *v == remove {
                        *v = keep;
                    }
                }
                self.triangles_of[keep as usize].push(f);
            }
        }
        let dead = &self.dead;
        self.triangles_of[keep as usize].retain(|&f| !dead[f as usize]);
        let (k, r) = (keep as usize, remove as usize);
        let (pk, pr) = (self.positions[k], self.positions[r]);
        let t = if pk == pr { 0.0 } else { ((at - pk).dot(pr - pk) / pk.distance_squared(pr)).clamp(0.0, 1.0) as f32 };
        self.colours[k] = std::array::from_fn(|ch| self.colours[k][ch] * (1.0 - t) + self.colours[r][ch] * t);
        self.positions[k] = at;
        let q = self.quadrics[r];
        self.quadrics[k].add(&q);
        self.removed[r] = true;
        self.version[k] += 1;
        shared.len()
    }

    /// The live triangles over the vertices they use, renumbered in order.
    fn into_mesh(self) -> Mesh {
        let mut number = vec![u32::MAX; self.positions.len()];
        let mut mesh = Mesh::default();
        for (f, t) in self.triangles.iter().enumerate() {
            if self.dead[f] {
                continue;
            }
            let renumbered = t.map(|v| {
                if number[v as usize] == u32::MAX {
                    number[v as usize] = mesh.positions.len() as u32;
                    mesh.positions.push(self.positions[v as usize].as_vec3());
                    mesh.colours.push(self.colours[v as usize]);
                }
                number[v as usize]
            });
            mesh.triangles.push(renumbered);
        }
        set_normals(&mut mesh);
        mesh
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::export::mesh::mesh_of;
    use crate::field::grid::sphere_grid;
    use glam::Vec3;

    fn volume(mesh: &Mesh) -> f32 {
        let signed = |t: &[u32; 3]| {
            let [a, b, c] = t.map(|v| mesh.positions[v as usize]);
            a.dot(b.cross(c)) / 6.0
        };
        mesh.triangles.iter().map(signed).sum()
    }

    #[test]
    fn a_sphere_decimated_tenfold_stays_a_closed_outward_sphere() {
        let full = mesh_of(&sphere_grid(32, &Default::default()), None, 20.0).unwrap();
        let target = full.triangles.len() / 10;
        let small = decimate(&full, target);
        assert!(small.triangles.len() <= target && small.triangles.len() + 2 >= target, "{}", small.triangles.len());
        assert!(edge_uses(&small.triangles).values().all(|&n| n == 2), "still closed and manifold");
        // Euler characteristic of a sphere: V - E + F = 2.
        let (v, e, f) =
            (small.positions.len() as i64, edge_uses(&small.triangles).len() as i64, small.triangles.len() as i64);
        assert_eq!(v - e + f, 2);
        let radius = |m: &Mesh| m.positions.iter().map(|p| p.length()).sum::<f32>() / m.positions.len() as f32;
        assert!((radius(&small) / radius(&full) - 1.0).abs() < 0.02, "{} vs {}", radius(&small), radius(&full));
        assert!((volume(&small) / volume(&full) - 1.0).abs() < 0.03, "{} vs {}", volume(&small), volume(&full));
        let outward = small.positions.iter().zip(&small.normals).filter(|(p, n)| p.dot(**n) > 0.0).count();
        assert_eq!(outward, small.positions.len(), "normals still point out");
        assert!(small.colours.iter().flatten().all(|c| (0.0..=1.0).contains(c)));
    }

    #[test]
    fn an_open_border_keeps_its_outline_and_a_small_target_changes_nothing() {
        // A flat square of 8 x 8 quads, z = 0: every collapse inside is free.
        let n = 9u32;
        let mut square = Mesh::default();
        for j in 0..n {
            for i in 0..n {
                square.positions.push(Vec3::new(i as f32, j as f32, 0.0));
                square.colours.push([0.5; 3]);
            }
        }
        for j in 0..n - 1 {
            for i in 0..n - 1 {
                let v = j * n + i;
                square.triangles.push([v, v + 1, v + n + 1]);
                square.triangles.push([v, v + n + 1, v + n]);
            }
        }
        set_normals(&mut square);
        assert_eq!(decimate(&square, 1000).triangles.len(), square.triangles.len());
        let small = decimate(&square, 20);
        assert!(small.triangles.len() < square.triangles.len() / 2);
        let border = |m: &Mesh| {
            let mut b: Vec<[i32; 2]> = m
                .positions
                .iter()
                .filter(|p| p.x == 0.0 || p.y == 0.0 || p.x == 8.0 || p.y == 8.0)
                .map(|p| [p.x as i32, p.y as i32])
                .collect();
            b.sort();
            b
        };
        assert_eq!(border(&small), border(&square), "every border vertex in place");
        let area: f32 = small
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|v| small.positions[v as usize]);
                (b - a).cross(c - a).z / 2.0
            })
            .sum();
        assert!((area - 64.0).abs() < 1e-3, "the square's area, no triangle folded: {area}");
    }
}
