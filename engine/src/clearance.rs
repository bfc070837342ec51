//! How far a point is from a triangle mesh at least: a lower bound read from a uniform grid.
//!
//! In: one object's triangles. Out: [`Clearance::at`], a distance no triangle is nearer
//! than to a point (0 where it cannot say). A random walk inside the object asks it before
//! each free flight ([`crate::simulated`]): a flight shorter than the clearance cannot meet
//! the mesh, so the ray query (the walk's cost) is skipped and the walk goes on exactly as
//! the query's miss would have let it — the same random numbers, the same walks. Deep inside
//! a large object most flights are such.
//!
//! The grid marks every cell a triangle may touch (its bounding box, thinned by the
//! triangle's plane), then gives each cell its Chebyshev ring distance k to the nearest
//! marked cell (a breadth-first pass over the 26 neighbours): any point of the cell is then
//! at least (k − 1) cells from any triangle. Why by hand: a signed-distance crate gives exact
//! distances at a far higher build cost, and a conservative bound is all a skip needs.

use glam::Vec3;

/// Cells along the grid's longest side.
const CELLS: f32 = 64.0;

/// A lower bound on the distance to an object's triangles, per cell of a grid.
#[derive(Debug, Clone)]
pub struct Clearance {
    /// The grid's lowest corner (one cell below the triangles' bounds).
    lo: Vec3,
    /// Cell edge (scene units) and its inverse.
    h: f32,
    inv_h: f32,
    dims: [usize; 3],
    /// Per cell, the distance (scene units) no triangle is nearer than to any of its points.
    bound: Vec<f32>,
}

impl Clearance {
    /// The grid over `triangles`' bounds, padded by a cell on every side.
    pub fn new(triangles: &[[Vec3; 3]]) -> Clearance {
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for v in triangles.iter().flatten() {
            lo = lo.min(*v);
            hi = hi.max(*v);
        }
        if triangles.is_empty() || !(hi - lo).is_finite() {
            return Clearance {
                lo: Vec3::ZERO,
                h: 1.0,
                inv_h: 1.0,
                dims: [1, 1, 1],
                bound: vec![0.0],
            };
        }
        let h = ((hi - lo).max_element() / CELLS).max(f32::MIN_POSITIVE.sqrt());
        let lo = lo - Vec3::splat(h);
        let dims = ((hi - lo) / h).to_array().map(|e| e.ceil() as usize + 1);
        let mut grid = Clearance {
            lo,
            h,
            inv_h: 1.0 / h,
            dims,
            bound: Vec::new(),
        };
        let marked = grid.touched(triangles);
        grid.bound = grid
            .rings(&marked)
            .into_iter()
            // A cell no ring reached (nothing marked) says nothing.
            .map(|k| {
                if k == u32::MAX {
                    0.0
                } else {
                    k.saturating_sub(1) as f32 * h
                }
            })
            .collect();
        grid
    }

    /// A distance no triangle is nearer than to `p`: 0 outside the grid.
    #[inline]
    pub fn at(&self, p: Vec3) -> f32 {
        let c = (p - self.lo) * self.inv_h;
        if !(c.cmpge(Vec3::ZERO).all()) {
            return 0.0;
        }
        let [x, y, z] = c.to_array().map(|e| e as usize);
        let [nx, ny, nz] = self.dims;
        if x >= nx || y >= ny || z >= nz {
            return 0.0;
        }
        self.bound[(z * ny + y) * nx + x]
    }

    /// Whether a flight of length `len` from `p` certainly meets no triangle: shorter than
    /// the clearance by a margin far above the float error of a ray query.
    #[inline]
    pub fn clear(&self, p: Vec3, len: f32) -> bool {
        len + 1e-3 * self.h < self.at(p)
    }

    fn index(&self, [x, y, z]: [usize; 3]) -> usize {
        (z * self.dims[1] + y) * self.dims[0] + x
    }

    /// The cells a triangle may touch: in its bounding box and within half a cell's
    /// diagonal of its plane.
    fn touched(&self, triangles: &[[Vec3; 3]]) -> Vec<bool> {
        let mut marked = vec![false; self.dims.iter().product()];
        let reach = 0.5 * 3f32.sqrt() * self.h * 1.01;
        for t in triangles {
            let (a, b) = (t[0].min(t[1]).min(t[2]), t[0].max(t[1]).max(t[2]));
            let first = self.cell_of(a).map(|c| c.saturating_sub(1));
            let last = self.cell_of(b).map(|c| c + 1);
            let n = (t[1] - t[0]).cross(t[2] - t[0]).normalize_or_zero();
            for z in first[2]..=last[2].min(self.dims[2] - 1) {
                for y in first[1]..=last[1].min(self.dims[1] - 1) {
                    for x in first[0]..=last[0].min(self.dims[0] - 1) {
                        let centre =
                            self.lo + (Vec3::new(x as f32, y as f32, z as f32) + 0.5) * self.h;
                        if n == Vec3::ZERO || (centre - t[0]).dot(n).abs() <= reach {
                            marked[self.index([x, y, z])] = true;
                        }
                    }
                }
            }
        }
        marked
    }

    /// The cell holding `p`, clamped to the grid.
    fn cell_of(&self, p: Vec3) -> [usize; 3] {
        let c = ((p - self.lo) * self.inv_h).max(Vec3::ZERO).to_array();
        std::array::from_fn(|a| (c[a] as usize).min(self.dims[a] - 1))
    }

    /// Each cell's Chebyshev ring distance to the nearest marked cell (0 on one, u32::MAX
    /// where nothing is marked), by a breadth-first pass over the 26 neighbours.
    fn rings(&self, marked: &[bool]) -> Vec<u32> {
        let [nx, ny, nz] = self.dims;
        let mut ring = vec![u32::MAX; marked.len()];
        let mut front: Vec<usize> = (0..marked.len()).filter(|&i| marked[i]).collect();
        for &i in &front {
            ring[i] = 0;
        }
        let mut k = 0;
        while !front.is_empty() {
            k += 1;
            let mut next = Vec::new();
            for &i in &front {
                let (x, y, z) = (i % nx, (i / nx) % ny, i / (nx * ny));
                for z2 in z.saturating_sub(1)..=(z + 1).min(nz - 1) {
                    for y2 in y.saturating_sub(1)..=(y + 1).min(ny - 1) {
                        for x2 in x.saturating_sub(1)..=(x + 1).min(nx - 1) {
                            let j = self.index([x2, y2, z2]);
                            if ring[j] == u32::MAX {
                                ring[j] = k;
                                next.push(j);
                            }
                        }
                    }
                }
            }
            front = next;
        }
        ring
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The distance from `p` to triangle `t` (brute force over the plane and the edges).
    fn distance(p: Vec3, t: &[Vec3; 3]) -> f32 {
        let n = (t[1] - t[0]).cross(t[2] - t[0]).normalize();
        let q = p - n * (p - t[0]).dot(n);
        let inside = (0..3).all(|k| {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            (b - a).cross(q - a).dot(n) >= 0.0
        });
        if inside {
            return (p - q).length();
        }
        (0..3)
            .map(|k| {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                let s = ((p - a).dot(b - a) / (b - a).length_squared()).clamp(0.0, 1.0);
                (p - (a + (b - a) * s)).length()
            })
            .fold(f32::INFINITY, f32::min)
    }

    #[test]
    fn the_bound_never_exceeds_the_true_distance_and_is_useful_inside() {
        // A box of 12 triangles and a slanted one through it.
        let (lo, hi) = (Vec3::new(-1.0, -0.5, -2.0), Vec3::new(1.0, 0.5, 2.0));
        let c = |x: usize, y: usize, z: usize| {
            Vec3::new([lo.x, hi.x][x], [lo.y, hi.y][y], [lo.z, hi.z][z])
        };
        let mut tris = Vec::new();
        for (a, b, cc, d) in [
            (c(0, 0, 0), c(1, 0, 0), c(1, 1, 0), c(0, 1, 0)),
            (c(0, 0, 1), c(0, 1, 1), c(1, 1, 1), c(1, 0, 1)),
            (c(0, 0, 0), c(0, 1, 0), c(0, 1, 1), c(0, 0, 1)),
            (c(1, 0, 0), c(1, 0, 1), c(1, 1, 1), c(1, 1, 0)),
            (c(0, 0, 0), c(0, 0, 1), c(1, 0, 1), c(1, 0, 0)),
            (c(0, 1, 0), c(1, 1, 0), c(1, 1, 1), c(0, 1, 1)),
        ] {
            tris.push([a, b, cc]);
            tris.push([a, cc, d]);
        }
        tris.push([
            Vec3::new(-0.9, -0.4, 1.0),
            Vec3::new(0.9, 0.4, 1.5),
            Vec3::new(0.0, 0.4, 0.2),
        ]);
        let grid = Clearance::new(&tris);
        let mut s = 99u64;
        let mut rnd = || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f32 / (1u64 << 53) as f32
        };
        let mut useful = 0;
        for _ in 0..20000 {
            let p = Vec3::new(3.0 * rnd() - 1.5, 2.0 * rnd() - 1.0, 5.0 * rnd() - 2.5);
            let truth = tris
                .iter()
                .map(|t| distance(p, t))
                .fold(f32::INFINITY, f32::min);
            let b = grid.at(p);
            assert!(b <= truth, "at {p}: bound {b} > distance {truth}");
            useful += (b > 0.5 * truth && truth > 0.1) as u32;
        }
        assert!(useful > 1000, "the bound is rarely useful: {useful}");
        // Outside the grid it says nothing.
        assert_eq!(grid.at(Vec3::splat(10.0)), 0.0);
        assert!(!grid.clear(Vec3::ZERO, 10.0));
    }
}
