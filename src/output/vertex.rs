//! Per-vertex radiosity: patch values averaged onto the vertices of the patch mesh.
//!
//! Radiosity is solved per patch (piecewise constant). For display and baking, each mesh
//! vertex gets the area-weighted average of the radiosity of the patches around it, and the
//! mesh is shaded by interpolating between vertices (Gouraud shading; Cohen and Greenberg,
//! "The Hemi-Cube", SIGGRAPH 1985, section 5; Cohen and Wallace, *Radiosity and Realistic
//! Image Synthesis*, 1993, section 8.3.1 "nodal averaging").
//!
//! Averaging must not blur across real edges, so the patches around a position are split
//! into *smoothing groups*:
//!
//! 1. **Welding.** The patch mesh shares vertices only within one scene face. Vertices of
//!    different faces at the same position (bitwise, or within `1e-6 ×` the scene diagonal)
//!    are first welded into one position, so that a floor made of several coplanar quads
//!    shades as one surface. Welding is transitive (union-find); the welded position is the
//!    one of the lowest-numbered vertex.
//! 2. **Grouping.** Around one welded position, two patches are *compatible* when they have
//!    the same material and their normals differ by at most the crease angle
//!    ([`DEFAULT_CREASE_DEG`] by default). Groups are the connected components of that
//!    relation (so a fan of patches bending slowly around a vertex stays one group).
//!    Back-to-back surfaces have opposite normals and are never grouped.
//! 3. **Splitting.** Each (position, group) pair becomes one output vertex. A position on a
//!    crease or a material boundary therefore yields several output vertices with the same
//!    position and different values and normals.
//!
//! The output triangles are the patch triangles ([`PatchSet::triangles`]) in the same
//! order, remapped to the output vertices, and output vertices are numbered in order of
//! first use by those triangles, so the mesh is deterministic. Each output vertex carries
//! the normalised area-weighted average normal of its group, and a radiosity from the
//! group's patches by one of two rules ([`Nodal`]):
//!
//! - **average**: the area-weighted average (nodal averaging), for meshes of patches of
//!   one size;
//! - **linear**: the value at the vertex of the least-squares plane through the patches'
//!   (centroid, radiosity) pairs, clamped to the range of those radiosities. Each patch's
//!   value is its mean, which for a field linear over the patch is the value at its
//!   centroid, so the plane reproduces linear fields exactly whatever the patch sizes.
//!   Area weights do not: where a leaf 16 times larger meets small ones (the hierarchy's
//!   meshes, where elements are small only along shadows and contacts), the large leaf
//!   sets the vertex to the value of a point far from it, 12% off on the floor 8 mm from
//!   the short block of the Cornell box. Groups whose centroids do not span a plane fall
//!   back to the area-weighted average.

use std::collections::HashMap;

use glam::{DVec3, Vec3};

use crate::mesh::{PatchSet, NONE};

/// Default crease angle in degrees: patches whose normals differ by more are not averaged.
pub const DEFAULT_CREASE_DEG: f32 = 30.0;

/// Positions closer than this fraction of the scene diagonal are welded.
pub const WELD_RELATIVE: f64 = 1e-6;

/// Radiosity per output vertex, with the mesh to display it on.
///
/// All per-vertex arrays have the same length; output vertex `k` is `positions[k]`,
/// `normals[k]`, `rgb[k]`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct VertexRadiosity {
    /// Vertex positions (scene units).
    pub positions: Vec<Vec3>,
    /// Unit vertex normals (area-weighted average over the vertex's smoothing group).
    pub normals: Vec<Vec3>,
    /// Linear radiosity per RGB channel (the solver's units).
    pub rgb: Vec<[f32; 3]>,
    /// Triangles as indices into the vertex arrays, counter-clockwise seen from the front.
    pub triangles: Vec<[u32; 3]>,
    /// The patch each triangle belongs to.
    pub patch_of_triangle: Vec<u32>,
    /// Whether each triangle's surface emits (empty: none does); the preview's automatic
    /// exposure leaves emitters out.
    pub emits: Vec<bool>,
    /// Whether each triangle is one side of a two-sided face, lying on the other side's
    /// triangle (empty: none is); the preview draws only the side facing the camera.
    pub two_sided: Vec<bool>,
}

impl VertexRadiosity {
    /// Number of vertices, after checking that positions, normals and colours agree;
    /// `path` names the file being written in the error.
    pub fn checked_len(&self, path: &std::path::Path) -> crate::error::Result<usize> {
        let n = self.positions.len();
        if self.normals.len() != n || self.rgb.len() != n {
            return Err(crate::error::Error::Output {
                path: path.to_path_buf(),
                msg: format!(
                    "inconsistent bake: {n} positions, {} normals, {} colours",
                    self.normals.len(),
                    self.rgb.len()
                ),
            });
        }
        Ok(n)
    }

    /// Number of vertices.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// True when there are no vertices.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }
}

/// How a vertex's radiosity is made from the patches of its smoothing group.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Nodal {
    /// Area-weighted average.
    Average,
    /// Least-squares plane through the patch centroids, clamped to their range.
    Linear,
}

/// Averages the patch radiosity `b` (one RGB value per patch) onto the vertices of the
/// patch mesh, without averaging across creases sharper than `crease_deg` degrees or
/// across different materials (see the module docs for the exact rules); the
/// [`Nodal::Average`] rule.
///
/// # Panics
/// If `b` does not hold one value per patch: that is a bug in the caller, not bad input.
pub fn interpolate(patches: &PatchSet, b: &[[f64; 3]], crease_deg: f32) -> VertexRadiosity {
    interpolate_with(patches, b, crease_deg, Nodal::Average)
}

/// [`interpolate`] with the vertex rule `nodal`.
///
/// # Panics
/// If `b` does not hold one value per patch: that is a bug in the caller, not bad input.
pub fn interpolate_with(
    patches: &PatchSet,
    b: &[[f64; 3]],
    crease_deg: f32,
    nodal: Nodal,
) -> VertexRadiosity {
    assert_eq!(
        b.len(),
        patches.len(),
        "interpolate: {} radiosity values for {} patches",
        b.len(),
        patches.len()
    );
    let tol = WELD_RELATIVE * patches.diagonal;
    // Output positions are f32 (the files' type): welded as they will be written.
    let v32: Vec<Vec3> = patches.vertices.iter().map(|v| v.as_vec3()).collect();
    let weld = weld_positions(&v32, tol as f32);
    let cos_crease = crease_cosine(crease_deg);

    // Incidence lists (CSR): for each welded position, the sorted distinct patches whose
    // triangles touch it. Built from the triangles, so every later lookup succeeds.
    let nv = patches.vertices.len();
    let mut start = vec![0usize; nv + 1];
    for t in &patches.triangles {
        for &c in t {
            start[weld[c as usize] as usize + 1] += 1;
        }
    }
    for k in 0..nv {
        start[k + 1] += start[k];
    }
    let mut incident = vec![0u32; start[nv]];
    let mut fill = start.clone();
    for (t, &p) in patches.triangles.iter().zip(&patches.tri_patch) {
        for &c in t {
            let r = weld[c as usize] as usize;
            incident[fill[r]] = p;
            fill[r] += 1;
        }
    }
    // Sort and deduplicate each list in place; `len[r]` is its distinct length.
    let mut len = vec![0usize; nv];
    for r in 0..nv {
        let list = &mut incident[start[r]..start[r + 1]];
        list.sort_unstable();
        let mut n = 0;
        for k in 0..list.len() {
            if n == 0 || list[k] != list[n - 1] {
                list[n] = list[k];
                n += 1;
            }
        }
        len[r] = n;
    }

    // Smoothing groups: union-find over each incidence list; `label` holds, for each
    // incidence, the local index of its group's first member.
    let mut label = vec![0u32; incident.len()];
    let mut parent: Vec<usize> = Vec::new();
    for r in 0..nv {
        let list = &incident[start[r]..start[r] + len[r]];
        parent.clear();
        parent.extend(0..list.len());
        for a in 0..list.len() {
            for b2 in a + 1..list.len() {
                if compatible(patches, list[a] as usize, list[b2] as usize, cos_crease) {
                    union(&mut parent, a, b2);
                }
            }
        }
        for a in 0..list.len() {
            label[start[r] + a] = find(&mut parent, a) as u32;
        }
    }

    // Number output vertices in order of first use by the triangles.
    let mut out_id = vec![NONE; incident.len()];
    let mut out = VertexRadiosity {
        triangles: Vec::with_capacity(patches.triangles.len()),
        patch_of_triangle: patches.tri_patch.clone(),
        emits: patches
            .tri_patch
            .iter()
            .map(|&p| patches.materials[patches.material[p as usize] as usize].is_emitter())
            .collect(),
        two_sided: if patches.twin.is_empty() {
            Vec::new()
        } else {
            patches
                .tri_patch
                .iter()
                .map(|&p| patches.twin_of(p as usize).is_some())
                .collect()
        },
        ..Default::default()
    };
    let mut root_of_out: Vec<u32> = Vec::new();
    for (t, &p) in patches.triangles.iter().zip(&patches.tri_patch) {
        let mut tri = [0u32; 3];
        for (k, &c) in t.iter().enumerate() {
            let r = weld[c as usize] as usize;
            let list = &incident[start[r]..start[r] + len[r]];
            // Present by construction: (r, p) was inserted from this very triangle.
            let at = list.binary_search(&p).unwrap_or(0);
            let slot = start[r] + label[start[r] + at] as usize;
            if out_id[slot] == NONE {
                out_id[slot] = root_of_out.len() as u32;
                root_of_out.push(r as u32);
            }
            tri[k] = out_id[slot];
        }
        out.triangles.push(tri);
    }

    // Accumulate each group's area-weighted radiosity and normal.
    let n_out = root_of_out.len();
    let mut sum_b = vec![DVec3::ZERO; n_out];
    let mut sum_n = vec![DVec3::ZERO; n_out];
    let mut sum_w = vec![0.0f64; n_out];
    // Unweighted fallbacks, for groups made only of zero-area patches.
    let mut plain_b = vec![DVec3::ZERO; n_out];
    let mut plain_n = vec![DVec3::ZERO; n_out];
    let mut count = vec![0u32; n_out];
    // The members of each group, for the linear rule.
    let mut members: Vec<Vec<u32>> = match nodal {
        Nodal::Linear => vec![Vec::new(); n_out],
        Nodal::Average => Vec::new(),
    };
    for r in 0..nv {
        for a in 0..len[r] {
            let id = out_id[start[r] + label[start[r] + a] as usize];
            if id == NONE {
                continue;
            }
            let (id, p) = (id as usize, incident[start[r] + a] as usize);
            let area = patches.area[p];
            let w = if area.is_finite() && area > 0.0 {
                area
            } else {
                0.0
            };
            let bp = DVec3::from_array(b[p]);
            let np = patches.normal[p];
            sum_b[id] += bp * w;
            sum_n[id] += np * w;
            sum_w[id] += w;
            plain_b[id] += bp;
            plain_n[id] += np;
            count[id] += 1;
            if nodal == Nodal::Linear && w > 0.0 {
                members[id].push(p as u32);
            }
        }
    }
    out.positions = root_of_out.iter().map(|&r| v32[r as usize]).collect();
    out.rgb = Vec::with_capacity(n_out);
    out.normals = Vec::with_capacity(n_out);
    for id in 0..n_out {
        let (mut avg, n) = if sum_w[id] > 0.0 {
            (sum_b[id] / sum_w[id], sum_n[id])
        } else {
            (plain_b[id] / f64::from(count[id].max(1)), plain_n[id])
        };
        if nodal == Nodal::Linear && members[id].len() >= 3 {
            let at = patches.vertices[root_of_out[id] as usize];
            if let Some(v) = plane_value(patches, b, &members[id], at, n.normalize_or_zero()) {
                avg = v;
            }
        }
        out.rgb.push([avg.x as f32, avg.y as f32, avg.z as f32]);
        out.normals.push(n.normalize_or_zero().as_vec3());
    }
    out
}

/// Scalar fields per output vertex, on the mesh of [`interpolate`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct VertexFields {
    /// The output mesh (positions, normals, triangles), the same as [`interpolate`] makes;
    /// its `rgb` is zero.
    pub mesh: VertexRadiosity,
    /// One array per field, in the order given, one value per output vertex.
    pub values: Vec<Vec<f32>>,
}

/// Interpolates any number of scalar patch fields (one value per patch each) onto the
/// output vertices by `nodal`, exactly as [`interpolate_with`] does radiosity (three
/// fields at a time: the mesh and its smoothing groups depend only on the patches).
///
/// # Panics
/// If a field does not hold one value per patch: that is a bug in the caller.
pub fn interpolate_fields(
    patches: &PatchSet,
    fields: &[&[f64]],
    crease_deg: f32,
    nodal: Nodal,
) -> VertexFields {
    let mut out = VertexFields::default();
    for (k, chunk) in fields.chunks(3).enumerate() {
        let b: Vec<[f64; 3]> = (0..patches.len())
            .map(|i| {
                let at = |c: usize| chunk.get(c).map_or(0.0, |f| f[i]);
                [at(0), at(1), at(2)]
            })
            .collect();
        let v = interpolate_with(patches, &b, crease_deg, nodal);
        for c in 0..chunk.len() {
            out.values.push(v.rgb.iter().map(|x| x[c]).collect());
        }
        if k == 0 {
            out.mesh = v;
        }
    }
    if fields.is_empty() {
        out.mesh = interpolate_with(patches, &vec![[0.0; 3]; patches.len()], crease_deg, nodal);
    }
    out.mesh.rgb.iter_mut().for_each(|c| *c = [0.0; 3]);
    out
}

/// The value at `at` of the least-squares plane through the (centroid, radiosity) pairs
/// of `members`, in the tangent plane of normal `n`, per channel, clamped to the members'
/// range; `None` when the centroids do not span a plane (the normal equations' determinant
/// is below `1e-9` of its scale).
fn plane_value(
    patches: &PatchSet,
    b: &[[f64; 3]],
    members: &[u32],
    at: DVec3,
    n: DVec3,
) -> Option<DVec3> {
    if n == DVec3::ZERO {
        return None;
    }
    let t = n.any_orthonormal_vector();
    let s = n.cross(t);
    let pts: Vec<(f64, f64)> = members
        .iter()
        .map(|&p| {
            let d = patches.centroid[p as usize] - at;
            (d.dot(t), d.dot(s))
        })
        .collect();
    // Coordinates in units of the mean distance, for a scale-free determinant test.
    let scale = pts.iter().map(|&(x, y)| x.hypot(y)).sum::<f64>() / pts.len() as f64;
    if !(scale > 0.0 && scale.is_finite()) {
        return None;
    }
    let mut m = [[0.0f64; 3]; 3];
    let mut rhs = [DVec3::ZERO; 3];
    let (mut lo, mut hi) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
    for (&(x, y), &p) in pts.iter().zip(members) {
        let row = [1.0, x / scale, y / scale];
        let bp = DVec3::from_array(b[p as usize]);
        lo = lo.min(bp);
        hi = hi.max(bp);
        for i in 0..3 {
            for j in 0..3 {
                m[i][j] += row[i] * row[j];
            }
            rhs[i] += bp * row[i];
        }
    }
    let det = |m: &[[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(&m);
    let k = pts.len() as f64;
    // Also refuses a NaN determinant.
    if d.is_nan() || d.abs() <= 1e-9 * k * k * k {
        return None;
    }
    // Cramer's rule for the constant term: the first column replaced by the right side.
    let value = DVec3::new(
        det(&[
            [rhs[0].x, m[0][1], m[0][2]],
            [rhs[1].x, m[1][1], m[1][2]],
            [rhs[2].x, m[2][1], m[2][2]],
        ]),
        det(&[
            [rhs[0].y, m[0][1], m[0][2]],
            [rhs[1].y, m[1][1], m[1][2]],
            [rhs[2].y, m[2][1], m[2][2]],
        ]),
        det(&[
            [rhs[0].z, m[0][1], m[0][2]],
            [rhs[1].z, m[1][1], m[1][2]],
            [rhs[2].z, m[2][1], m[2][2]],
        ]),
    ) / d;
    value.is_finite().then(|| value.clamp(lo, hi))
}

/// Cosine of the crease angle, slightly lowered so that coplanar patches whose normals
/// differ by rounding still group at a crease angle of 0.
fn crease_cosine(crease_deg: f32) -> f64 {
    let deg = if crease_deg.is_nan() {
        DEFAULT_CREASE_DEG
    } else {
        crease_deg.clamp(0.0, 180.0)
    };
    f64::from(deg).to_radians().cos() - 1e-6
}

/// Same material and normals within the crease angle.
fn compatible(patches: &PatchSet, i: usize, j: usize, cos_crease: f64) -> bool {
    patches.material[i] == patches.material[j]
        && patches.normal[i].dot(patches.normal[j]) >= cos_crease
}

/// Union-find root with path halving.
fn find(parent: &mut [usize], mut a: usize) -> usize {
    while parent[a] != a {
        parent[a] = parent[parent[a]];
        a = parent[a];
    }
    a
}

/// Joins the sets of `a` and `b`; the lower index becomes the root, for determinism.
fn union(parent: &mut [usize], a: usize, b: usize) {
    let (ra, rb) = (find(parent, a), find(parent, b));
    if ra < rb {
        parent[rb] = ra;
    } else if rb < ra {
        parent[ra] = rb;
    }
}

/// For each vertex, the lowest-numbered vertex it is welded to: vertices bitwise equal or
/// closer than `tol`, closed transitively. A uniform grid of cell size `tol` finds the
/// candidates among the 27 cells around each vertex.
fn weld_positions(vertices: &[Vec3], tol: f32) -> Vec<u32> {
    let n = vertices.len();
    let mut parent: Vec<usize> = (0..n).collect();
    let bits = |p: Vec3| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()];
    if !(tol > 0.0 && tol.is_finite()) {
        let mut first: HashMap<[u32; 3], usize> = HashMap::with_capacity(n);
        for (v, &p) in vertices.iter().enumerate() {
            let u = *first.entry(bits(p)).or_insert(v);
            union(&mut parent, u, v);
        }
    } else {
        let cell = |p: Vec3| -> [i64; 3] {
            let q = (p.as_dvec3() / f64::from(tol)).floor();
            [q.x as i64, q.y as i64, q.z as i64]
        };
        // Per cell, a linked list of the vertices inserted so far (head, next).
        let mut head: HashMap<[i64; 3], u32> = HashMap::with_capacity(n);
        let mut next = vec![NONE; n];
        let tol2 = tol * tol;
        for (v, &p) in vertices.iter().enumerate() {
            let c = cell(p);
            for dz in -1..=1i64 {
                for dy in -1..=1i64 {
                    for dx in -1..=1i64 {
                        let key = [
                            c[0].wrapping_add(dx),
                            c[1].wrapping_add(dy),
                            c[2].wrapping_add(dz),
                        ];
                        let mut u = head.get(&key).copied().unwrap_or(NONE);
                        while u != NONE {
                            let q = vertices[u as usize];
                            if bits(q) == bits(p) || q.distance_squared(p) <= tol2 {
                                union(&mut parent, u as usize, v);
                            }
                            u = next[u as usize];
                        }
                    }
                }
            }
            next[v] = head.insert(c, v as u32).unwrap_or(NONE);
        }
    }
    (0..n).map(|v| find(&mut parent, v) as u32).collect()
}

/// Hand-made patch sets for the tests of this module and its siblings.
#[cfg(test)]
pub(crate) mod testing {
    use super::*;
    use crate::scene::Material;

    /// Adds a planar quad face `p` (corners counter-clockwise seen from the front) split
    /// into `n x n` patches with their own vertices, as `PatchSet::build` does.
    pub fn add_quad(set: &mut PatchSet, p: [Vec3; 4], material: u32, n: usize) {
        let p = p.map(|q| q.as_dvec3());
        let face = set.face.last().map_or(0, |f| f + 1);
        let base = set.vertices.len() as u32;
        for b in 0..=n {
            for a in 0..=n {
                let (s, t) = (a as f64 / n as f64, b as f64 / n as f64);
                let q = p[0] * ((1.0 - s) * (1.0 - t))
                    + p[1] * (s * (1.0 - t))
                    + p[2] * (s * t)
                    + p[3] * ((1.0 - s) * t);
                set.vertices.push(q);
            }
        }
        let at = |a: usize, b: usize| base + (b * (n + 1) + a) as u32;
        for b in 0..n {
            for a in 0..n {
                let c = [at(a, b), at(a + 1, b), at(a + 1, b + 1), at(a, b + 1)];
                let q: Vec<DVec3> = c.iter().map(|&k| set.vertices[k as usize]).collect();
                let cr = (q[1] - q[0]).cross(q[2] - q[0]) + (q[2] - q[0]).cross(q[3] - q[0]);
                let id = set.area.len() as u32;
                set.corners.push(c);
                set.area.push(cr.length() * 0.5);
                set.normal.push(cr.normalize());
                set.centroid.push((q[0] + q[1] + q[2] + q[3]) / 4.0);
                set.material.push(material);
                set.object.push(0);
                set.face.push(face);
                set.triangles.push([c[0], c[1], c[2]]);
                set.triangles.push([c[0], c[2], c[3]]);
                set.tri_patch.extend([id, id]);
            }
        }
        let (mut lo, mut hi) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
        for &v in &set.vertices {
            lo = lo.min(v);
            hi = hi.max(v);
        }
        set.diagonal = (hi - lo).length();
        set.magnitude = lo.abs().max(hi.abs()).max_element();
    }

    /// An empty patch set with `k` grey materials.
    pub fn empty(k: usize) -> PatchSet {
        PatchSet {
            scene: "test".into(),
            materials: (0..k)
                .map(|m| Material {
                    name: format!("m{m}"),
                    rho: [0.5; 3],
                    emit: [0.0; 3],
                    thermal: None,
                    two_sided: false,
                })
                .collect(),
            objects: vec!["test".into()],
            ..Default::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::testing::{add_quad, empty};
    use super::*;

    fn v(x: f32, y: f32, z: f32) -> Vec3 {
        Vec3::new(x, y, z)
    }

    /// Number of distinct output vertices at position `p`.
    fn at_position(out: &VertexRadiosity, p: Vec3) -> usize {
        out.positions
            .iter()
            .filter(|&&q| q.distance(p) < 1e-5)
            .count()
    }

    #[test]
    fn constant_field_is_reproduced_everywhere() {
        // Furnace-like: a closed box, every patch with the same radiosity.
        let mut set = empty(1);
        let c = |x: f32, y: f32, z: f32| v(x, y, z);
        let faces = [
            [c(0., 0., 0.), c(0., 1., 0.), c(1., 1., 0.), c(1., 0., 0.)],
            [c(0., 0., 1.), c(1., 0., 1.), c(1., 1., 1.), c(0., 1., 1.)],
            [c(0., 0., 0.), c(1., 0., 0.), c(1., 0., 1.), c(0., 0., 1.)],
            [c(0., 1., 0.), c(0., 1., 1.), c(1., 1., 1.), c(1., 1., 0.)],
            [c(0., 0., 0.), c(0., 0., 1.), c(0., 1., 1.), c(0., 1., 0.)],
            [c(1., 0., 0.), c(1., 1., 0.), c(1., 1., 1.), c(1., 0., 1.)],
        ];
        for f in faces {
            add_quad(&mut set, f, 0, 3);
        }
        let b0 = [0.25, 1.5, 3.0];
        let b = vec![b0; set.len()];
        let out = interpolate(&set, &b, DEFAULT_CREASE_DEG);
        assert!(!out.is_empty());
        for rgb in &out.rgb {
            for k in 0..3 {
                assert!((f64::from(rgb[k]) - b0[k]).abs() <= 1e-6 * b0[k], "{rgb:?}");
            }
        }
        // Box corners: three faces at 90 degrees meet, so three output vertices each.
        assert_eq!(at_position(&out, v(0., 0., 0.)), 3);
        assert_eq!(out.triangles.len(), set.triangles.len());
        assert_eq!(out.patch_of_triangle, set.tri_patch);
        for n in &out.normals {
            assert!((n.length() - 1.0).abs() < 1e-5);
        }
    }

    /// Two unit quads side by side in the plane y = 0 (facing +y), sharing the edge x = 1.
    fn two_coplanar(m0: u32, m1: u32) -> PatchSet {
        let mut set = empty(2);
        add_quad(
            &mut set,
            [v(0., 0., 0.), v(0., 0., 1.), v(1., 0., 1.), v(1., 0., 0.)],
            m0,
            2,
        );
        add_quad(
            &mut set,
            [v(1., 0., 0.), v(1., 0., 1.), v(2., 0., 1.), v(2., 0., 0.)],
            m1,
            2,
        );
        set
    }

    #[test]
    fn coplanar_faces_with_one_material_weld() {
        let set = two_coplanar(0, 0);
        // Radiosity 1 on the left face, 3 on the right.
        let b: Vec<[f64; 3]> = (0..set.len())
            .map(|i| if set.face[i] == 0 { [1.0; 3] } else { [3.0; 3] })
            .collect();
        let out = interpolate(&set, &b, DEFAULT_CREASE_DEG);
        // 3 x 3 + 3 x 3 vertices, of which the shared row of 3 is welded.
        assert_eq!(out.len(), 15);
        for z in [0.0, 0.5, 1.0] {
            let p = v(1.0, 0.0, z);
            assert_eq!(at_position(&out, p), 1);
            let k = out
                .positions
                .iter()
                .position(|&q| q.distance(p) < 1e-5)
                .unwrap();
            assert_eq!(
                out.rgb[k], [2.0; 3],
                "equal areas on both sides average to 2"
            );
            assert!(out.normals[k].distance(Vec3::Y) < 1e-6);
        }
    }

    #[test]
    fn near_coincident_vertices_weld() {
        let mut set = empty(1);
        add_quad(
            &mut set,
            [v(0., 0., 0.), v(0., 0., 1.), v(1., 0., 1.), v(1., 0., 0.)],
            0,
            1,
        );
        let e = 1e-7;
        add_quad(
            &mut set,
            [
                v(1. + e, 0., 0.),
                v(1., 0., 1. + e),
                v(2., 0., 1.),
                v(2., 0., 0.),
            ],
            0,
            1,
        );
        let out = interpolate(&set, &vec![[1.0; 3]; set.len()], DEFAULT_CREASE_DEG);
        assert_eq!(out.len(), 6);
    }

    #[test]
    fn different_materials_do_not_weld() {
        let set = two_coplanar(0, 1);
        let b: Vec<[f64; 3]> = (0..set.len())
            .map(|i| if set.face[i] == 0 { [1.0; 3] } else { [3.0; 3] })
            .collect();
        let out = interpolate(&set, &b, DEFAULT_CREASE_DEG);
        assert_eq!(out.len(), 18);
        for (k, p) in out.positions.iter().enumerate() {
            if (p.x - 1.0).abs() < 1e-6 {
                assert!(
                    out.rgb[k] == [1.0; 3] || out.rgb[k] == [3.0; 3],
                    "{:?}",
                    out.rgb[k]
                );
            }
        }
        assert_eq!(at_position(&out, v(1.0, 0.0, 0.5)), 2);
    }

    #[test]
    fn crease_splits_and_wide_crease_angle_merges() {
        // A floor (facing +y) and a wall (facing +x) meeting at x = 0 at 90 degrees.
        let mut set = empty(1);
        add_quad(
            &mut set,
            [v(0., 0., 0.), v(0., 0., 1.), v(1., 0., 1.), v(1., 0., 0.)],
            0,
            2,
        );
        add_quad(
            &mut set,
            [v(0., 0., 0.), v(0., 1., 0.), v(0., 1., 1.), v(0., 0., 1.)],
            0,
            2,
        );
        assert!(set.normal[0].distance(DVec3::Y) < 1e-6);
        assert!(set.normal[set.len() - 1].distance(DVec3::X) < 1e-6);
        let b: Vec<[f64; 3]> = (0..set.len())
            .map(|i| if set.face[i] == 0 { [1.0; 3] } else { [3.0; 3] })
            .collect();

        let out = interpolate(&set, &b, DEFAULT_CREASE_DEG);
        assert_eq!(out.len(), 18);
        assert_eq!(at_position(&out, v(0., 0., 0.5)), 2);
        for (k, p) in out.positions.iter().enumerate() {
            if p.x == 0.0 && p.y == 0.0 {
                let n = out.normals[k];
                let expect = if out.rgb[k] == [1.0; 3] {
                    Vec3::Y
                } else {
                    Vec3::X
                };
                assert!(out.rgb[k] == [1.0; 3] || out.rgb[k] == [3.0; 3]);
                assert!(n.distance(expect) < 1e-6, "{n:?}");
            }
        }

        // At a crease angle above 90 degrees the edge is smoothed.
        let out = interpolate(&set, &b, 100.0);
        assert_eq!(out.len(), 15);
        let k = out
            .positions
            .iter()
            .position(|&q| q == v(0., 0., 0.5))
            .unwrap();
        assert_eq!(out.rgb[k], [2.0; 3]);
        assert!(out.normals[k].distance(Vec3::new(1.0, 1.0, 0.0).normalize()) < 1e-6);
    }

    #[test]
    fn back_to_back_faces_stay_apart() {
        let mut set = empty(1);
        add_quad(
            &mut set,
            [v(0., 0., 0.), v(0., 0., 1.), v(1., 0., 1.), v(1., 0., 0.)],
            0,
            1,
        );
        add_quad(
            &mut set,
            [v(0., 0., 0.), v(1., 0., 0.), v(1., 0., 1.), v(0., 0., 1.)],
            0,
            1,
        );
        let out = interpolate(&set, &[[1.0; 3], [2.0; 3]], 179.0);
        assert_eq!(out.len(), 8);
    }

    #[test]
    fn output_is_deterministic_and_follows_triangle_order() {
        let set = two_coplanar(0, 0);
        let b: Vec<[f64; 3]> = (0..set.len()).map(|i| [i as f64, 0.0, 1.0]).collect();
        let a = interpolate(&set, &b, DEFAULT_CREASE_DEG);
        assert_eq!(a, interpolate(&set, &b, DEFAULT_CREASE_DEG));
        // First use order: the first triangle uses vertices 0, 1, 2.
        assert_eq!(a.triangles[0], [0, 1, 2]);
        let mut seen = 0;
        for t in &a.triangles {
            for &k in t {
                assert!(k <= seen);
                if k == seen {
                    seen += 1;
                }
            }
        }
        assert_eq!(seen as usize, a.len());
    }

    #[test]
    fn linear_rule_reproduces_linear_fields_on_mixed_sizes() {
        // One unit quad split 2 x 2 beside one split 4 x 4, a field linear in x and z.
        let mut set = empty(2);
        add_quad(
            &mut set,
            [v(0., 0., 0.), v(0., 0., 1.), v(1., 0., 1.), v(1., 0., 0.)],
            0,
            2,
        );
        add_quad(
            &mut set,
            [v(1., 0., 0.), v(1., 0., 1.), v(2., 0., 1.), v(2., 0., 0.)],
            0,
            4,
        );
        let field = |p: DVec3| 1.0 + 0.5 * p.x + 0.25 * p.z;
        let b: Vec<[f64; 3]> = (0..set.len())
            .map(|i| [field(set.centroid[i]); 3])
            .collect();
        let lin = interpolate_with(&set, &b, DEFAULT_CREASE_DEG, Nodal::Linear);
        let avg = interpolate(&set, &b, DEFAULT_CREASE_DEG);
        let k = lin
            .positions
            .iter()
            .position(|&q| q.distance(v(1.0, 0.0, 0.5)) < 1e-6)
            .unwrap();
        let want = field(DVec3::new(1.0, 0.0, 0.5));
        assert!(
            (f64::from(lin.rgb[k][0]) - want).abs() < 1e-5,
            "{:?}",
            lin.rgb[k]
        );
        // The area-weighted average is pulled toward the large patch's centroid.
        let k2 = avg
            .positions
            .iter()
            .position(|&q| q.distance(v(1.0, 0.0, 0.5)) < 1e-6)
            .unwrap();
        assert!((f64::from(avg.rgb[k2][0]) - want).abs() > 0.05);
        // Values stay within the range of the patches around each vertex.
        let (lo, hi) = b
            .iter()
            .fold((f64::MAX, f64::MIN), |(l, h), x| (l.min(x[0]), h.max(x[0])));
        assert!(lin
            .rgb
            .iter()
            .all(|c| f64::from(c[0]) >= lo - 1e-6 && f64::from(c[0]) <= hi + 1e-6));
    }

    #[test]
    fn scalar_fields_interpolate_as_radiosity() {
        let set = two_coplanar(0, 1);
        let f: Vec<Vec<f64>> = (0..4)
            .map(|c| (0..set.len()).map(|i| (i * 7 + c) as f64).collect())
            .collect();
        let refs: Vec<&[f64]> = f.iter().map(|x| &x[..]).collect();
        let out = interpolate_fields(&set, &refs, DEFAULT_CREASE_DEG, Nodal::Average);
        let b: Vec<[f64; 3]> = (0..set.len())
            .map(|i| [f[0][i], f[1][i], f[2][i]])
            .collect();
        let want = interpolate(&set, &b, DEFAULT_CREASE_DEG);
        assert_eq!(out.mesh.positions, want.positions);
        assert_eq!(out.mesh.triangles, want.triangles);
        assert!(out.mesh.rgb.iter().all(|c| *c == [0.0; 3]));
        assert_eq!(out.values.len(), 4);
        for c in 0..3 {
            let col: Vec<f32> = want.rgb.iter().map(|x| x[c]).collect();
            assert_eq!(out.values[c], col);
        }
        let b: Vec<[f64; 3]> = (0..set.len()).map(|i| [f[3][i]; 3]).collect();
        let col: Vec<f32> = interpolate(&set, &b, DEFAULT_CREASE_DEG)
            .rgb
            .iter()
            .map(|x| x[0])
            .collect();
        assert_eq!(out.values[3], col);
    }

    #[test]
    fn cornell_box_interpolates() {
        let scene = crate::scene::Scene::load("cornell").unwrap();
        let set = PatchSet::build(&scene, crate::mesh::Resolution::Patches(500)).unwrap();
        let b: Vec<[f64; 3]> = (0..set.len()).map(|i| set.rho(i)).collect();
        let out = interpolate(&set, &b, DEFAULT_CREASE_DEG);
        assert_eq!(out.triangles.len(), set.triangles.len());
        assert!(out.len() < set.vertices.len(), "welding removed nothing");
        // Every vertex takes the colour of its material: no mixing across materials.
        let colours: Vec<[f32; 3]> = set
            .materials
            .iter()
            .map(|m| [m.rho[0] as f32, m.rho[1] as f32, m.rho[2] as f32])
            .collect();
        for rgb in &out.rgb {
            assert!(
                colours
                    .iter()
                    .any(|c| (0..3).all(|k| (c[k] - rgb[k]).abs() < 1e-6)),
                "{rgb:?}"
            );
        }
    }
}
