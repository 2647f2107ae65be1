//! The hemicube (Cohen and Greenberg 1985; Cohen and Wallace 1993, §5.2; radiosidade.md,
//! "Hemi-cubo"): a whole row from one point per patch, deterministically.
//!
//! A unit half-cube is centred on the centroid `x` of patch i, its top face at height 1
//! along the normal and its four side faces at distance 1 (top `[-1, 1]²`, sides
//! `[-1, 1] x [0, 1]`). The top face is cut into `res x res` cells and each side into
//! `res x res/2`. Each cell carries its *delta form factor*, the differential factor from
//! `x` to the cell:
//!
//! - top face, cell centre `(u, v, 1)`: `ΔF = ΔA / (π (u² + v² + 1)²)`;
//! - side face, cell centre at height `z` and lateral offset `v`:
//!   `ΔF = z ΔA / (π (v² + z² + 1)²)`,
//!
//! with `ΔA = (2/res)²` the cell area; the deltas sum to 1 up to `O(1/res²)`. Where the
//! original projects patches onto the faces with a z-buffer, here the patch seen through a
//! cell is found by one ray through the cell centre (Embree's first hit), which is what
//! the z-buffer computes at the cell centre. `F_ij` is the sum of the deltas of the cells
//! that see the front of patch j.
//!
//! Two approximations make its known failures (Baum, Rushmeier and Winget 1989):
//! - **proximity**: the whole patch i is represented by its centroid, so the estimate is
//!   `F(x_c → P_j)`, not the area average. For near or adjacent patches the point factor
//!   varies strongly over i and the error does not shrink with `res`;
//! - **aliasing**: a patch is seen by whole cells or not at all. A small or distant patch
//!   covers few cells, and its factor jumps as cell centres cross its outline.
//!
//! There is no randomness: the same inputs give the same row, and the reported standard
//! error is 0. That 0 is not a statement of accuracy: both errors are deterministic biases
//! that the row itself cannot estimate (the study in `docs/ESTIMATORS.md` measures them
//! against closed forms).

use super::hemisphere::basis;
use super::{Context, Entry, Estimator, Row};

/// Hemicube estimator.
#[derive(Clone, Debug)]
pub struct Hemicube {
    /// Cells per side of the top face (rounded up to an even number); the sides have
    /// `res x res/2` cells, so a row casts `3 res²` rays.
    pub res: usize,
}

impl Default for Hemicube {
    fn default() -> Self {
        Hemicube { res: 64 }
    }
}

impl Hemicube {
    /// The resolution actually used: even and at least 2.
    pub fn resolution(&self) -> usize {
        (self.res.max(2) + 1) & !1
    }

    /// Every cell as `(direction in the local frame (t, b, n), delta form factor)`.
    pub fn cells(&self) -> Vec<([f64; 3], f64)> {
        let res = self.resolution();
        let h = 2.0 / res as f64;
        let da = h * h;
        let pi = std::f64::consts::PI;
        let mut out = Vec::with_capacity(3 * res * res);
        for a in 0..res {
            let u = -1.0 + (a as f64 + 0.5) * h;
            for b in 0..res {
                let v = -1.0 + (b as f64 + 0.5) * h;
                let d = u * u + v * v + 1.0;
                out.push(([u, v, 1.0], da / (pi * d * d)));
            }
        }
        // Four sides: local x = ±1 or y = ±1, height z in (0, 1).
        for a in 0..res {
            let v = -1.0 + (a as f64 + 0.5) * h;
            for c in 0..res / 2 {
                let z = (c as f64 + 0.5) * h;
                let d = v * v + z * z + 1.0;
                let w = z * da / (pi * d * d);
                out.push(([1.0, v, z], w));
                out.push(([-1.0, v, z], w));
                out.push(([v, 1.0, z], w));
                out.push(([v, -1.0, z], w));
            }
        }
        out
    }
}

impl Estimator for Hemicube {
    fn name(&self) -> String {
        format!("hemicube(res={})", self.resolution())
    }

    fn row(&self, ctx: &Context, i: usize, row: &mut Row, _: &mut super::Scratch) {
        let p = ctx.patches;
        let n_i = p.normal[i];
        let (t, b) = basis(n_i.as_vec3());
        let (t, b) = (t.as_dvec3(), b.as_dvec3());
        let x = p.centroid[i];
        let mut acc: Vec<(u32, f64)> = Vec::new();
        for (d, w) in self.cells() {
            let dir = (t * d[0] + b * d[1] + n_i * d[2]).normalize();
            row.rays += 1;
            if let Some(h) = ctx.vis.first_hit(x, n_i, dir) {
                if h.patch as usize != i && p.normal[h.patch as usize].dot(dir) < 0.0 {
                    acc.push((h.patch, w));
                }
            }
        }
        acc.sort_unstable_by_key(|e| e.0);
        let mut k = 0;
        while k < acc.len() {
            let j = acc[k].0;
            let mut f = 0.0;
            while k < acc.len() && acc[k].0 == j {
                f += acc[k].1;
                k += 1;
            }
            row.entries.push(Entry { j, f, se: 0.0 });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn delta_form_factors_sum_to_one() {
        for res in [2, 8, 64, 256] {
            let s: f64 = Hemicube { res }.cells().iter().map(|c| c.1).sum();
            // Midpoint rule on smooth integrands: O(1/res²).
            assert!((s - 1.0).abs() < 1.0 / (res * res) as f64, "res {res}: {s}");
        }
        assert_eq!(Hemicube { res: 7 }.resolution(), 8);
        assert_eq!(Hemicube { res: 8 }.cells().len(), 3 * 64);
    }
}
