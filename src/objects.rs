//! Form factors between objects: the patch matrix aggregated over the scene's objects.
//!
//! Heat-transfer and lighting users ask for surface-to-surface factors between named
//! surfaces (Radiance's `rfluxmtx` gives them per modifier), not between patches. With
//! `I`, `J` objects (sets of patches, [`crate::scene::Scene::objects`]) and
//! `A_I = sum_{i in I} A_i`, the factor from `I` to `J` is the area-weighted mean of its
//! patches' factors to all of `J`:
//!
//! `F_IJ = (1 / A_I) sum_{i in I} A_i sum_{j in J} F_ij`
//!
//! (radiosidade.md, "Fator de Forma": the fraction of the energy leaving `I`, uniformly
//! diffuse, that reaches `J`). It keeps the patch matrix's laws: `A_I F_IJ = A_J F_JI`
//! when the patches' factors are reciprocal, and the rows of a closed scene sum to 1.
//!
//! ## Standard errors
//! The sum `S_IJ = sum A_i F_ij` is propagated from the per-entry standard errors `s_ij`
//! (`stderr.mtx`) as the row sums are ([`crate::matrix::FormFactors::row_sum_stderr`]),
//! entries independent, added in quadrature, with one exception:
//!
//! - between two objects (`I != J`): `se(S_IJ)² = sum (A_i s_ij)²`;
//! - within one object (`I = J`), the two entries of a pair `(i, j)`, `(j, i)` are both in
//!   the sum. The estimators that compute the upper triangle and mirror it
//!   ([`crate::matrix::CsrBuilder::from_upper`]) make `A_i F_ij = A_j F_ji` the same random
//!   number, so the pair's errors add linearly: `se(S_II)² = sum_{i<j} (A_i s_ij +
//!   A_j s_ji)² + sum_i (A_i s_ii)²`. This is exact for mirrored entries and, for
//!   independent ones, larger than the truth by at most a factor `sqrt 2` (an error bar on
//!   the safe side).
//!
//! Then `se(F_IJ) = se(S_IJ) / A_I`. Entries within one row of a hemisphere or hemicube
//! estimate share their rays and are negatively correlated (a ray hits one patch or
//! another), so there too the quadrature sum is on the safe side.
//!
//! ## Files
//! [`ObjectFactors::objects_csv`], [`ObjectFactors::matrix_csv`] give the text of
//! `objects.csv` (`id,name,patches,area`), `objects_F.csv` and `objects_stderr.csv`: square
//! tables with a header row `from,NAME_0,NAME_1,...` and one row per source object, its
//! name first, so that `pandas.read_csv("objects_F.csv", index_col=0)` is the matrix with
//! its names (`df.loc["light", "floor"]`) and `numpy.loadtxt(..., delimiter=",",
//! skiprows=1, usecols=range(1, n + 1))` the bare array. Names are quoted as CSV quotes
//! them when they hold a comma or a quote.

use std::fmt::Write as _;

use crate::error::{Error, Result};
use crate::matrix::FormFactors;
use crate::mesh::PatchSet;
use crate::output::csv_field;

/// Most objects aggregated: the tables are dense, `n x n`; beyond this many (4 MB of
/// numbers per table, more than anyone reads as a table) they are not made.
pub const MAX_OBJECTS: usize = 1024;

/// Form factors between objects, with standard errors (see the [module docs](self)).
#[derive(Clone, Debug, PartialEq)]
pub struct ObjectFactors {
    /// Object names, in the scene's order.
    pub names: Vec<String>,
    /// Patches of each object.
    pub patches: Vec<usize>,
    /// Area of each object (sum of its patches' areas).
    pub area: Vec<f64>,
    /// `F_IJ`, row-major (`f[I * n + J]`).
    pub f: Vec<f64>,
    /// Standard error of each `F_IJ`, row-major.
    pub se: Vec<f64>,
}

impl ObjectFactors {
    /// Aggregates `ff` over the objects of `patches`. Refuses more than [`MAX_OBJECTS`]
    /// objects, a patch set whose object indices do not match its patches, and an object
    /// of zero area.
    pub fn aggregate(patches: &PatchSet, ff: &FormFactors) -> Result<ObjectFactors> {
        let n = patches.objects.len();
        let bad = |msg: String| Error::Scene {
            scene: patches.scene.clone(),
            msg,
        };
        if n > MAX_OBJECTS {
            return Err(bad(format!(
                "{n} objects: the object-to-object tables are made for at most {MAX_OBJECTS}"
            )));
        }
        if patches.object.len() != patches.len()
            || ff.len() != patches.len()
            || patches.object.iter().any(|&o| o as usize >= n)
        {
            return Err(bad(format!(
                "{} patches, {} object indices, {} objects, a {} x {0} matrix: they do not \
                 match",
                patches.len(),
                patches.object.len(),
                n,
                ff.len()
            )));
        }
        let mut count = vec![0usize; n];
        let mut area = vec![0.0f64; n];
        for i in 0..patches.len() {
            count[patches.object[i] as usize] += 1;
            area[patches.object[i] as usize] += patches.area[i];
        }
        if let Some(k) = (0..n).find(|&k| area[k].is_nan() || area[k] <= 0.0) {
            return Err(bad(format!(
                "object `{}` has area {} and {} patches: no factor from it is defined",
                patches.objects[k], area[k], count[k]
            )));
        }
        let mut sum = vec![0.0f64; n * n];
        let mut var = vec![0.0f64; n * n];
        let (ptr, cols) = (ff.f.indptr(), ff.f.indices());
        let data = ff.f.data();
        for i in 0..ff.len() {
            let oi = patches.object[i] as usize;
            let a_i = patches.area[i];
            for k in ptr.index(i)..ptr.index(i + 1) {
                let j = cols[k] as usize;
                let oj = patches.object[j] as usize;
                let cell = oi * n + oj;
                sum[cell] += a_i * data[k];
                let e = a_i * f64::from(ff.se[k]);
                if oi != oj || i == j {
                    var[cell] += e * e;
                    continue;
                }
                // Within one object: the pair (i, j), (j, i) once, errors added linearly.
                let back =
                    ff.f.nnz_index(j, i)
                        .map(|b| patches.area[j] * f64::from(ff.se[b.0]));
                match back {
                    Some(e_back) if i < j => var[cell] += (e + e_back) * (e + e_back),
                    Some(_) => {} // counted with (j, i)
                    None => var[cell] += e * e,
                }
            }
        }
        let f = (0..n * n).map(|c| sum[c] / area[c / n]).collect();
        let se = (0..n * n).map(|c| var[c].sqrt() / area[c / n]).collect();
        Ok(ObjectFactors {
            names: patches.objects.clone(),
            patches: count,
            area,
            f,
            se,
        })
    }

    /// Number of objects.
    pub fn len(&self) -> usize {
        self.names.len()
    }

    /// True when there are no objects.
    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }

    /// `F_IJ`.
    pub fn get(&self, from: usize, to: usize) -> f64 {
        self.f[from * self.len() + to]
    }

    /// Standard error of `F_IJ`.
    pub fn stderr(&self, from: usize, to: usize) -> f64 {
        self.se[from * self.len() + to]
    }

    /// Index of the object named `name`.
    pub fn index(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    /// `objects.csv`: `id,name,patches,area`, one row per object.
    pub fn objects_csv(&self) -> String {
        let mut o = String::from("id,name,patches,area\n");
        for k in 0..self.len() {
            let _ = writeln!(
                o,
                "{k},{},{},{:e}",
                csv_field(&self.names[k]),
                self.patches[k],
                self.area[k]
            );
        }
        o
    }

    /// A square table of `values` (row-major, `n x n`: [`ObjectFactors::f`] or
    /// [`ObjectFactors::se`]) with the objects' names: header `from,NAME...`, then per
    /// source object its name and its row.
    pub fn matrix_csv(&self, values: &[f64]) -> String {
        let n = self.len();
        let mut o = String::from("from");
        for name in &self.names {
            o.push(',');
            o.push_str(&csv_field(name));
        }
        o.push('\n');
        for i in 0..n {
            o.push_str(&csv_field(&self.names[i]));
            for v in &values[i * n..(i + 1) * n] {
                let _ = write!(o, ",{v:e}");
            }
            o.push('\n');
        }
        o
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::matrix::Entry;

    /// Four patches of areas 1, 2, 3, 4 in objects a = {0, 1}, b = {2, 3}.
    fn patches() -> PatchSet {
        PatchSet {
            scene: "t".into(),
            area: vec![1.0, 2.0, 3.0, 4.0],
            object: vec![0, 0, 1, 1],
            objects: vec!["a".into(), "b, c".into()],
            ..Default::default()
        }
    }

    fn e(j: u32, f: f64, se: f64) -> Entry {
        Entry { j, f, se }
    }

    #[test]
    fn aggregates_by_area_and_propagates_errors() {
        let rows = vec![
            vec![e(1, 0.1, 0.01), e(2, 0.2, 0.02), e(3, 0.3, 0.03)],
            vec![e(0, 0.05, 0.005), e(3, 0.4, 0.04)],
            vec![e(0, 0.5, 0.05)],
            vec![],
        ];
        let ff = FormFactors::from_rows(rows, vec![1.0, 2.0, 3.0, 4.0], 0, 0.0, "t".into(), 2);
        let o = ObjectFactors::aggregate(&patches(), &ff).unwrap();
        assert_eq!(o.patches, [2, 2]);
        assert_eq!(o.area, [3.0, 7.0]);
        let close = |x: f64, y: f64| (x - y).abs() <= 1e-15 * y.abs().max(1.0);
        // Standard errors are stored as f32.
        let r = |x: f64| f64::from(x as f32);
        // a -> a: (1 * 0.1 + 2 * 0.05) / 3; the pair (0, 1), (1, 0) adds linearly.
        assert!(close(o.get(0, 0), 0.2 / 3.0), "{}", o.get(0, 0));
        assert!(close(o.stderr(0, 0), (r(0.01) + 2.0 * r(0.005)) / 3.0));
        // a -> b: (1 * (0.2 + 0.3) + 2 * 0.4) / 3, errors in quadrature.
        assert!(close(o.get(0, 1), 1.3 / 3.0));
        let v: f64 = r(0.02).powi(2) + r(0.03).powi(2) + (2.0 * r(0.04)).powi(2);
        assert!(close(o.stderr(0, 1), v.sqrt() / 3.0));
        // b -> a: 3 * 0.5 / 7; b -> b: nothing stored.
        assert!(close(o.get(1, 0), 1.5 / 7.0));
        assert!(close(o.stderr(1, 0), 3.0 * r(0.05) / 7.0));
        assert_eq!((o.get(1, 1), o.stderr(1, 1)), (0.0, 0.0));
        // The tables, with the name holding a comma quoted.
        assert_eq!(
            o.objects_csv(),
            "id,name,patches,area\n0,a,2,3e0\n1,\"b, c\",2,7e0\n"
        );
        let text = o.matrix_csv(&o.f);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "from,a,\"b, c\"");
        assert!(
            lines[2] == format!("\"b, c\",{:e},0e0", 1.5 / 7.0),
            "{}",
            lines[2]
        );
        assert_eq!(lines.len(), 3);
    }

    #[test]
    fn inconsistent_inputs_are_refused_not_indexed() {
        let ff = FormFactors::from_rows(vec![vec![]; 4], vec![1.0; 4], 0, 0.0, "t".into(), 2);
        let mut p = patches();
        p.object.pop();
        let e = ObjectFactors::aggregate(&p, &ff).unwrap_err().to_string();
        assert!(e.contains("do not match"), "{e}");
        let mut p = patches();
        p.area[2] = 0.0;
        p.area[3] = 0.0;
        let e = ObjectFactors::aggregate(&p, &ff).unwrap_err().to_string();
        assert!(e.contains("object `b, c` has area 0"), "{e}");
    }
}
