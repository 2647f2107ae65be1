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
//! (`stderr.mtx`) as the row sums are ([`crate::matrix::FormFactors::row_sum_bar`]),
//! entries independent, added in quadrature, with one exception:
//!
//! - between two objects (`I != J`): `se(S_IJ)² = sum (A_i s_ij)²`;
//! - within one object (`I = J`), the two entries of a pair `(i, j)`, `(j, i)` are both in
//!   the sum. Where they are one random variable (they satisfy reciprocity to rounding in
//!   value and bar, [`crate::matrix::reciprocal_pairs`]: the estimators that compute the
//!   upper triangle and mirror it, [`crate::matrix::CsrBuilder::from_upper`]) the pair's
//!   errors add linearly, `(2 A_i s_ij)²`; otherwise as independent variances.
//!
//! Then `se(F_IJ) = se(S_IJ) / A_I`. Entries within one row of a hemisphere or hemicube
//! estimate share their rays and are negatively correlated (a ray hits one patch or
//! another), so there too the quadrature sum is on the safe side.
//!
//! Entries whose error is deterministic carry a bound `b_ij` instead (`bound.mtx`,
//! [`crate::matrix::Bar`]); bounds add linearly, `bound(S_IJ) = sum A_i b_ij` (both entries
//! of a pair counted), and `bound(F_IJ) = bound(S_IJ) / A_I`, written as
//! `objects_bound.csv`.
//!
//! ## Files
//! [`ObjectFactors::objects_csv`], [`ObjectFactors::matrix_csv`] give the text of
//! `objects.csv` (`id,name,patches,area`), `objects_F.csv`, `objects_stderr.csv` and
//! `objects_bound.csv`: square
//! tables with a header row `from,NAME_0,NAME_1,...` and one row per source object, its
//! name first, so that `pandas.read_csv("objects_F.csv", index_col=0)` is the matrix with
//! its names (`df.loc["light", "floor"]`) and `numpy.loadtxt(..., delimiter=",",
//! skiprows=1, usecols=range(1, n + 1))` the bare array. Names are quoted as CSV quotes
//! them when they hold a comma or a quote.

use std::fmt::Write as _;

use crate::error::{Error, Result};
use crate::matrix::{mirror, Bar, Csr, FormFactors};
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
    /// Bound on the deterministic error of each `F_IJ`, row-major.
    pub bound: Vec<f64>,
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
        let (zf, zse, _) = lump(&ff.f, &ff.se, &patches.area, &patches.object, n)?;
        let (mut f, mut se) = (vec![0.0f64; n * n], vec![0.0f64; n * n]);
        let mut bound = vec![0.0f64; n * n];
        let mut k = 0;
        for (i, row) in zf.outer_iterator().enumerate() {
            for (j, &v) in row.iter() {
                f[i * n + j] = v;
                se[i * n + j] = zse[k].se;
                bound[i * n + j] = zse[k].bound;
                k += 1;
            }
        }
        Ok(ObjectFactors {
            names: patches.objects.clone(),
            patches: count,
            area,
            f,
            se,
            bound,
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

    /// Bound on the deterministic error of `F_IJ`.
    pub fn bound(&self, from: usize, to: usize) -> f64 {
        self.bound[from * self.len() + to]
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

/// Factors between groups of patches (objects, or a thermal run's surfaces): `group[i]`
/// names patch i's group in `0..groups`.
/// Returns the zone matrix `F_SK = sum_{i in S, j in K} A_i F_ij / A_S` (CSR), its bars
/// (standard errors and bounds, module docs) and the zone areas. With each surface as one zone of uniform radiosity this is
/// the zonal model that the closed forms of the textbooks assume (Hottel and Sarofim 1967,
/// ch. 8; Modest, 3rd ed., sec. 6.3: "each surface isothermal with uniform radiosity").
/// Reciprocal pairs of patches (module docs) give reciprocal zone factors with coupled
/// errors: within one zone a pair counts twice, `(2 A_i s_ij)²`; the other terms add as
/// independent variances `(A_i s_ij)²`. Bounds add linearly.
pub fn lump(
    f: &Csr,
    se: &[f32],
    area: &[f64],
    group: &[u32],
    groups: usize,
) -> Result<(Csr, Vec<Bar>, Vec<f64>)> {
    let n = area.len();
    if f.rows() != n || se.len() != f.nnz() || group.len() != n {
        return Err(Error::Config(format!(
            "lump: {} rows, {} errors for {} factors, {} labels, {n} patches",
            f.rows(),
            se.len(),
            f.nnz(),
            group.len()
        )));
    }
    if let Some(i) = group.iter().position(|&g| g as usize >= groups) {
        return Err(Error::Config(format!(
            "patch {i}: surface {} of {groups}",
            group[i]
        )));
    }
    let mut a = vec![0.0; groups];
    for i in 0..n {
        a[group[i] as usize] += area[i];
    }
    let mut sum = vec![0.0; groups * groups];
    let mut var = vec![0.0; groups * groups];
    let mut bound = vec![0.0; groups * groups];
    let ptr = f.indptr();
    let ptr = ptr.to_proper();
    let (ind, val) = (f.indices(), f.data());
    for i in 0..n {
        let s = group[i] as usize;
        for e in ptr[i]..ptr[i + 1] {
            let j = ind[e] as usize;
            let k = group[j] as usize;
            sum[s * groups + k] += area[i] * val[e];
            let bar = Bar::of(se[e]);
            bound[s * groups + k] += area[i] * bar.bound;
            let v = (area[i] * bar.se).powi(2);
            // Only pairs within one group are coupled: their mirrors alone are looked up.
            let paired = s == k && mirror(f, se, area, i, e).is_some();
            match paired {
                true if j < i => {}
                true => var[s * groups + k] += 4.0 * v,
                false => var[s * groups + k] += v,
            }
        }
    }
    let mut t = crate::matrix::Triplets::new((groups, groups));
    let mut out_se = Vec::new();
    for s in 0..groups {
        for k in 0..groups {
            let v = sum[s * groups + k];
            if v > 0.0 {
                t.add_triplet(s, k, v / a[s]);
            }
        }
    }
    let zf: Csr = t.to_csr();
    // Standard errors in the CSR order of `zf`.
    for (s, row) in zf.outer_iterator().enumerate() {
        for (k, _) in row.iter() {
            out_se.push(Bar {
                se: var[s * groups + k].sqrt() / a[s],
                bound: bound[s * groups + k] / a[s],
            });
        }
    }
    Ok((zf, out_se, a))
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
