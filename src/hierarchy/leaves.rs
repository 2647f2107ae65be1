//! The leaves of the hierarchy as a mesh without cracks, for the output stage.
//!
//! Neighbouring leaves may sit at different depths, so a coarse leaf's edge can carry the
//! corners of finer neighbours (T-vertices); drawn as two triangles, it would leave a
//! crack there, and its values would jump. Every leaf is therefore triangulated with all
//! the vertices that lie on its boundary:
//!
//! - every leaf corner goes into one table keyed by its exact `f64` bits (splits compute
//!   an edge's midpoint from its end points, and roots are welded, so a point shared by
//!   neighbours has the same bits in each);
//! - the vertices on an edge `(a, b)` are found by looking up its midpoint and, when it
//!   is there, recursing into both halves: exactly the points finer neighbours made;
//! - a leaf with no such vertex is drawn as its own one or two triangles; one with some is
//!   fanned from a new vertex at its centre, through every boundary vertex in order.
//!
//! Every edge of the result is then shared by the two triangles on either side of it (the
//! test `watertight_input_gives_a_watertight_mesh`). The mesh goes out as a [`PatchSet`]
//! whose patches are the leaves, so the output module's per-vertex averaging
//! ([`crate::output::interpolate`]: welding, smoothing groups at creases and material
//! boundaries, area weights) applies unchanged; buried leaves get zero weight there, so
//! a floor vertex at the foot of a box is not darkened by the floor inside it.

use std::collections::HashMap;

use glam::DVec3;

use super::element::Elements;
use crate::mesh::{PatchSet, NONE};

fn key(p: DVec3) -> [u64; 3] {
    [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()]
}

/// The leaves of `e` as a patch set (patch `k` is leaf `leaves[k]`), with materials,
/// objects, faces and scale copied from the root patch set, and the radiosity of each.
pub fn leaf_mesh(
    e: &Elements,
    roots: &PatchSet,
    b: &[[f64; 3]],
) -> (PatchSet, Vec<[f64; 3]>, Vec<u32>) {
    let leaves: Vec<u32> = e.leaves().collect();
    let mut set = PatchSet {
        scene: roots.scene.clone(),
        materials: roots.materials.clone(),
        objects: roots.objects.clone(),
        diagonal: roots.diagonal,
        max_edge: roots.max_edge,
        ..Default::default()
    };
    let mut index: HashMap<[u64; 3], u32> = HashMap::new();
    let mut vertices: Vec<DVec3> = Vec::new();
    let mut id_of = |p: DVec3, vertices: &mut Vec<DVec3>| -> u32 {
        *index.entry(key(p)).or_insert_with(|| {
            vertices.push(p);
            (vertices.len() - 1) as u32
        })
    };
    let mut corner_ids: Vec<[u32; 4]> = Vec::with_capacity(leaves.len());
    for &l in &leaves {
        let c = e.corners(l);
        let mut ids = [NONE; 4];
        for (k, &p) in c.iter().enumerate() {
            ids[k] = id_of(p, &mut vertices);
        }
        corner_ids.push(ids);
    }
    let lookup: HashMap<[u64; 3], u32> = vertices
        .iter()
        .enumerate()
        .map(|(k, &p)| (key(p), k as u32))
        .collect();
    let mut values = Vec::with_capacity(leaves.len());
    let mut boundary: Vec<u32> = Vec::new();
    for (k, &l) in leaves.iter().enumerate() {
        let li = l as usize;
        let c = e.corners(l);
        let m = c.len();
        boundary.clear();
        for a in 0..m {
            boundary.push(corner_ids[k][a]);
            on_edge(c[a], c[(a + 1) % m], &lookup, &mut boundary);
        }
        let patch = set.area.len() as u32;
        let root = e.root[li] as usize;
        set.corners.push(corner_ids[k]);
        set.area.push(e.visible_area(l));
        set.normal.push(e.normal[li]);
        set.centroid.push(e.centre[li]);
        set.material.push(roots.material[root]);
        set.object.push(roots.object[root]);
        set.face.push(roots.face[root]);
        values.push(b[li]);
        if boundary.len() == m {
            let ids = corner_ids[k];
            set.triangles.push([ids[0], ids[1], ids[2]]);
            set.tri_patch.push(patch);
            if m == 4 {
                set.triangles.push([ids[0], ids[2], ids[3]]);
                set.tri_patch.push(patch);
            }
        } else {
            vertices.push(e.centre[li]);
            let centre = (vertices.len() - 1) as u32;
            for a in 0..boundary.len() {
                let b2 = boundary[(a + 1) % boundary.len()];
                set.triangles.push([centre, boundary[a], b2]);
                set.tri_patch.push(patch);
            }
        }
    }
    set.vertices = vertices;
    (set, values, leaves)
}

/// Appends, in order from `a` to `b`, the table's vertices strictly inside the edge
/// `(a, b)` that nested midpoint splits of it produce.
fn on_edge(a: DVec3, b: DVec3, lookup: &HashMap<[u64; 3], u32>, out: &mut Vec<u32>) {
    let mid = (a + b) * 0.5;
    if mid == a || mid == b {
        return;
    }
    if let Some(&m) = lookup.get(&key(mid)) {
        on_edge(a, mid, lookup, out);
        out.push(m);
        on_edge(mid, b, lookup, out);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formfactor::exact::Piece;

    /// Two unit squares side by side, one split twice on the shared side: the coarse one
    /// must be fanned through the T-vertices, and every interior edge shared by two
    /// triangles.
    #[test]
    fn t_vertices_are_fanned() {
        let mut e = Elements::default();
        let a = Piece::Quad([DVec3::ZERO, DVec3::X, DVec3::new(1.0, 1.0, 0.0), DVec3::Y]);
        let b = Piece::Quad([
            DVec3::X,
            DVec3::new(2.0, 0.0, 0.0),
            DVec3::new(2.0, 1.0, 0.0),
            DVec3::new(1.0, 1.0, 0.0),
        ]);
        e.add_root(a, DVec3::Z);
        e.add_root(b, DVec3::Z);
        let kids = e.split(1);
        e.split(kids[0]);
        let roots = PatchSet {
            material: vec![0, 0],
            object: vec![0, 0],
            face: vec![0, 1],
            ..Default::default()
        };
        let bvals = vec![[1.0; 3]; e.len()];
        let (set, _, leaves) = leaf_mesh(&e, &roots, &bvals);
        assert_eq!(leaves.len(), 1 + 3 + 4);
        // The coarse square has 2 T-vertices on its right edge, at y = 1/4 and 1/2:
        // fanned into 6 triangles.
        let coarse = set.tri_patch.iter().filter(|&&p| p == 0).count();
        assert_eq!(coarse, 6);
        let mut edges: HashMap<(u32, u32), i32> = HashMap::new();
        for t in &set.triangles {
            for k in 0..3 {
                let (u, v) = (t[k], t[(k + 1) % 3]);
                *edges.entry((u.min(v), u.max(v))).or_default() += 1;
            }
        }
        // Boundary edges of the 2 x 1 rectangle: 1 use; all others: 2.
        let boundary = |p: DVec3, q: DVec3| {
            (p.y == 0.0 && q.y == 0.0)
                || (p.y == 1.0 && q.y == 1.0)
                || (p.x == 0.0 && q.x == 0.0)
                || (p.x == 2.0 && q.x == 2.0)
        };
        for (&(u, v), &n) in &edges {
            let (p, q) = (set.vertices[u as usize], set.vertices[v as usize]);
            assert_eq!(n, if boundary(p, q) { 1 } else { 2 }, "edge {p} {q}");
        }
    }
}
