//! Polygons meshed as written: any simple polygon (convex or concave, any number of
//! corners) turned into triangles that cover exactly its area, well shaped for the patch
//! mesher.
//!
//! The polygon is projected onto its best-fit plane: the Newell normal (Newell's method,
//! Sutherland, Sproull and Schumacker 1974, "A characterization of ten hidden-surface
//! algorithms", and Tampieri, "Newell's method for computing the plane equation of a
//! polygon", *Graphics Gems III* 1992), through the corners' centroid. There it must be
//! simple: no two edges that are not neighbours may cross or touch, no corner may fold an
//! edge back onto the previous one; anything else is refused with a message (the OBJ loader
//! adds the file and line), never triangulated into overlapping pieces.
//!
//! The triangulation is the constrained Delaunay triangulation of the corners with the
//! polygon's edges as constraints (Chew 1989, "Constrained Delaunay triangulations",
//! *Algorithmica* 4; through the `spade` crate, whose predicates are exact), keeping the
//! triangles inside the polygon. Of all triangulations of the corners it maximises the
//! smallest angle; for a quadrilateral it is the split along the better diagonal. When
//! that still leaves a sliver, a triangle with an angle under [`SLIVER_DEG`] (an n-gon
//! approximating a disk has nothing else: any triangulation of its corners is a fan of
//! slivers), and the polygon is planar, Steiner points are added by Delaunay refinement
//! (Ruppert 1995, "A Delaunay refinement algorithm for quality 2-dimensional mesh
//! generation", *J. Algorithms* 18; Shewchuk 2002, "Delaunay refinement algorithms for
//! triangular mesh generation", *CGTA* 22) until every angle is at least [`MIN_ANGLE_DEG`] (the
//! polygon's own corners sharper than that excepted). Points added on an edge are put on the
//! 3D edge itself, points inside on the best-fit plane.
//!
//! A polygon whose corners leave the best-fit plane by more than [`PLANARITY`] of its size
//! is not planar: it is split along the Delaunay diagonals of its projection, with no new
//! points, and the caller warns.
//!
//! Why a constrained Delaunay triangulation rather than plain ear clipping: ear clipping
//! only picks a triangulation of the given corners, and a disk written as one 128-corner
//! face has no good one; the refinement that fixes that needs the Delaunay structure
//! anyway, and `spade` provides both with exact predicates.

use glam::DVec3;
use spade::handles::{FixedFaceHandle, InnerTag};
use spade::Triangulation;
use spade::{AngleLimit, ConstrainedDelaunayTriangulation, Point2, RefinementParameters};

/// Largest distance of a corner from the best-fit plane, as a fraction of the polygon's size
/// (its bounding-box diagonal), for the polygon to count as planar.
pub const PLANARITY: f64 = 1e-2;

/// Smallest angle (degrees) the triangles of a planar polygon are refined to.
pub const MIN_ANGLE_DEG: f64 = 25.0;

/// A triangulation of the corners alone whose smallest angle is below this (degrees) is
/// refined; above it, the corners' own triangles are kept (fewer faces, and the patch mesher
/// keeps their shape).
pub const SLIVER_DEG: f64 = 15.0;

/// Largest number of corners a polygon may have (the simplicity test is quadratic).
pub const MAX_CORNERS: usize = 1 << 14;

/// Distance, as a fraction of the polygon's size, at which two edges count as touching.
const TOUCH: f64 = 1e-9;

/// A polygon as triangles.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Meshed {
    /// Points added by the refinement; index `corners + k` in [`Meshed::triangles`] is
    /// `extra[k]`.
    pub extra: Vec<DVec3>,
    /// Triangles, counter-clockwise seen from the side the Newell normal points to:
    /// indices into the polygon's corners, then into `extra`.
    pub triangles: Vec<[usize; 3]>,
    /// Set when the polygon is not planar: the largest distance of a corner from the
    /// best-fit plane, relative to the polygon's size.
    pub non_planar: Option<f64>,
    /// Where each point of `extra` lies, for [`Meshed::corner_weights`].
    pub extra_at: Vec<Place>,
    /// The corners in the best-fit plane's coordinates (scaled to the polygon's size), as
    /// the triangulation saw them.
    pub plane: Vec<[f64; 2]>,
}

/// Where a point added by the refinement lies in its polygon.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Place {
    /// On the edge from corner `k` to corner `k + 1` (cyclically), at parameter `t`.
    Edge(usize, f64),
    /// Inside, at these coordinates of [`Meshed::plane`].
    Inside([f64; 2]),
}

impl Meshed {
    /// Weights of the polygon's corners that make the added point `k` (`extra[k]`):
    /// `(corner, weight)` pairs summing to 1, by which any value given at the corners (the
    /// OBJ's texture coordinates) is carried to the point. On an edge, the two ends
    /// linearly; inside, Floater's mean value coordinates ("Mean value coordinates",
    /// *CAGD* 20, 2003; for non-convex polygons Hormann and Floater, "Mean value
    /// coordinates for arbitrary planar polygons", *ACM TOG* 25, 2006), in the plane the
    /// polygon was triangulated in. Both reproduce a value that is an affine function of
    /// the position exactly (texture coordinates projected onto a plane, as Blender's UV
    /// projections make them), and agree with the linear interpolation along each edge,
    /// so the texture is continuous across the polygon's triangles and its neighbours.
    pub fn corner_weights(&self, k: usize) -> Vec<(usize, f64)> {
        let n = self.plane.len();
        match self.extra_at[k] {
            Place::Edge(e, t) => vec![(e, 1.0 - t), ((e + 1) % n, t)],
            Place::Inside(x) => mean_value_weights(&self.plane, x),
        }
    }
}

/// Mean value coordinates of `x` with respect to the polygon `q` (see
/// [`Meshed::corner_weights`]): `w_i = (tan(a_(i-1)/2) + tan(a_i/2)) / |q_i - x|`, with
/// `a_i` the signed angle at `x` from `q_i` to `q_(i+1)`, normalised to sum 1. A point on
/// a corner gets that corner alone, one on an edge its two ends.
pub fn mean_value_weights(q: &[[f64; 2]], x: [f64; 2]) -> Vec<(usize, f64)> {
    let n = q.len();
    let d: Vec<[f64; 2]> = q.iter().map(|c| [c[0] - x[0], c[1] - x[1]]).collect();
    let r: Vec<f64> = d.iter().map(|v| v[0].hypot(v[1])).collect();
    let scale = r.iter().copied().fold(0.0, f64::max);
    if let Some(i) = (0..n).find(|&i| r[i] <= 1e-14 * scale) {
        return vec![(i, 1.0)];
    }
    // tan(a_i / 2) = (r_i r_(i+1) - d_i . d_(i+1)) / (d_i x d_(i+1)).
    let mut tan_half = vec![0.0; n];
    for i in 0..n {
        let j = (i + 1) % n;
        let cross = d[i][0] * d[j][1] - d[i][1] * d[j][0];
        let dot = d[i][0] * d[j][0] + d[i][1] * d[j][1];
        if cross.abs() <= 1e-14 * r[i] * r[j] {
            if dot < 0.0 {
                // On the edge from q_i to q_(i+1).
                let t = r[i] / (r[i] + r[j]);
                return vec![(i, 1.0 - t), (j, t)];
            }
            continue; // angle 0: the edge is seen end-on, tan = 0
        }
        tan_half[i] = (r[i] * r[j] - dot) / cross;
    }
    let w: Vec<f64> = (0..n)
        .map(|i| (tan_half[(i + n - 1) % n] + tan_half[i]) / r[i])
        .collect();
    let sum: f64 = w.iter().sum();
    w.into_iter()
        .enumerate()
        .filter(|&(_, x)| x != 0.0)
        .map(|(i, x)| (i, x / sum))
        .collect()
}

/// Newell normal of a polygon: its direction is the polygon's normal (counter-clockwise
/// corners seen from its tip), its length twice the area of a planar polygon.
pub fn newell(p: &[DVec3]) -> DVec3 {
    let mut n = DVec3::ZERO;
    for k in 0..p.len() {
        let (a, b) = (p[k], p[(k + 1) % p.len()]);
        n += DVec3::new(
            (a.y - b.y) * (a.z + b.z),
            (a.z - b.z) * (a.x + b.x),
            (a.x - b.x) * (a.y + b.y),
        );
    }
    n
}

/// `(b - a) x (c - a)` in 2D: positive when `a, b, c` turn counter-clockwise.
fn orient(a: [f64; 2], b: [f64; 2], c: [f64; 2]) -> f64 {
    (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
}

/// Distance from `p` to the segment `a b`, and the segment parameter of the nearest point.
fn point_segment(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> (f64, f64) {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let len2 = dx * dx + dy * dy;
    let t = if len2 > 0.0 {
        (((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let (x, y) = (a[0] + t * dx - p[0], a[1] + t * dy - p[1]);
    ((x * x + y * y).sqrt(), t)
}

/// Distance between the segments `a b` and `c d` (0 when they cross).
fn segment_segment(a: [f64; 2], b: [f64; 2], c: [f64; 2], d: [f64; 2]) -> f64 {
    let (o1, o2) = (orient(a, b, c), orient(a, b, d));
    let (o3, o4) = (orient(c, d, a), orient(c, d, b));
    if o1 * o2 < 0.0 && o3 * o4 < 0.0 {
        return 0.0;
    }
    point_segment(a, c, d)
        .0
        .min(point_segment(b, c, d).0)
        .min(point_segment(c, a, b).0)
        .min(point_segment(d, a, b).0)
}

/// Smallest angle of a 2D triangle, in degrees.
fn min_angle_deg(a: [f64; 2], b: [f64; 2], c: [f64; 2]) -> f64 {
    let len = |p: [f64; 2], q: [f64; 2]| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt();
    let (la, lb, lc) = (len(b, c), len(c, a), len(a, b));
    let area2 = orient(a, b, c).abs();
    // sin(angle at A) = 2 area / (b c); the smallest angle is opposite the shortest edge,
    // and is at most 60 degrees, so the arcsine is unambiguous.
    let (l1, l2) = if la <= lb && la <= lc {
        (lb, lc)
    } else if lb <= lc {
        (lc, la)
    } else {
        (la, lb)
    };
    (area2 / (l1 * l2)).clamp(0.0, 1.0).asin().to_degrees()
}

/// Checks that the projected polygon `q` is simple; says what is wrong otherwise.
fn check_simple(q: &[[f64; 2]]) -> Result<(), String> {
    let n = q.len();
    for k in 0..n {
        let (a, b, c) = (q[(k + n - 1) % n], q[k], q[(k + 1) % n]);
        // An edge folding back along the previous one (a spike of zero width).
        let (u, v) = ([b[0] - a[0], b[1] - a[1]], [c[0] - b[0], c[1] - b[1]]);
        let (lu, lv) = (u[0].hypot(u[1]), v[0].hypot(v[1]));
        let cross = u[0] * v[1] - u[1] * v[0];
        let dot = u[0] * v[0] + u[1] * v[1];
        if cross.abs() <= TOUCH * lu.max(lv) && dot < 0.0 {
            return Err(format!(
                "the polygon folds back on itself at corner {} (two edges overlap): it is \
                 not a simple polygon",
                k + 1
            ));
        }
    }
    for k in 0..n {
        let (a, b) = (q[k], q[(k + 1) % n]);
        for m in (k + 2)..n {
            if k == 0 && m == n - 1 {
                continue; // neighbours through corner 0
            }
            let (c, d) = (q[m], q[(m + 1) % n]);
            if segment_segment(a, b, c, d) <= TOUCH {
                return Err(format!(
                    "edges {}-{} and {}-{} of the polygon cross or touch (seen along its \
                     normal): it is self-intersecting, not a simple polygon",
                    k + 1,
                    (k + 1) % n + 1,
                    m + 1,
                    (m + 1) % n + 1
                ));
            }
        }
    }
    Ok(())
}

/// The inner faces of `cdt` inside the polygon: those not reachable from the outer face
/// without crossing a constraint edge (the polygon's edges are all constraints).
fn inside_faces(
    cdt: &ConstrainedDelaunayTriangulation<Point2<f64>>,
) -> Vec<FixedFaceHandle<InnerTag>> {
    let mut outside = vec![false; cdt.num_all_faces()];
    let mut stack = Vec::new();
    for face in cdt.inner_faces() {
        let touches_outer = face
            .adjacent_edges()
            .iter()
            .any(|e| e.rev().face().is_outer() && !e.is_constraint_edge());
        if touches_outer {
            outside[face.fix().index()] = true;
            stack.push(face.fix());
        }
    }
    while let Some(f) = stack.pop() {
        for e in cdt.face(f).adjacent_edges() {
            if e.is_constraint_edge() {
                continue;
            }
            if let Some(g) = e.rev().face().as_inner() {
                let gi = g.fix().index();
                if !outside[gi] {
                    outside[gi] = true;
                    stack.push(g.fix());
                }
            }
        }
    }
    cdt.inner_faces()
        .map(|f| f.fix())
        .filter(|f| !outside[f.index()])
        .collect()
}

/// True when the corners `p` lie on one line (within `1e-10` of their extent): a polygon
/// with no area at all, as opposed to one whose signed area cancels (a bow-tie).
pub fn collinear(p: &[DVec3]) -> bool {
    let Some(&a) = p.first() else {
        return true;
    };
    let far = p
        .iter()
        .copied()
        .max_by(|x, y| {
            (*x - a)
                .length_squared()
                .total_cmp(&(*y - a).length_squared())
        })
        .unwrap_or(a);
    let axis = far - a;
    let len = axis.length();
    if len == 0.0 {
        return true;
    }
    p.iter()
        .all(|&x| (x - a).cross(axis).length() <= 1e-10 * len * len)
}

/// Meshes the polygon with corners `p` (at least 3, consecutive corners distinct, with a
/// non-zero Newell normal). Returns what is wrong when the polygon is not simple.
pub fn mesh(p: &[DVec3]) -> Result<Meshed, String> {
    let n = p.len();
    if n < 3 {
        return Err(format!("a polygon needs 3 corners, found {n}"));
    }
    if n > MAX_CORNERS {
        return Err(format!(
            "the polygon has {n} corners, more than the {MAX_CORNERS} accepted"
        ));
    }
    let normal = newell(p);
    let (lo, hi) = p
        .iter()
        .fold((p[0], p[0]), |(lo, hi), &x| (lo.min(x), hi.max(x)));
    let size = (hi - lo).length();
    if !(normal.length() > 0.0 && size > 0.0 && normal.is_finite() && size.is_finite()) {
        return Err("the polygon has no area".into());
    }
    let nz = normal.normalize();
    let e1 = nz.any_orthonormal_vector();
    let e2 = nz.cross(e1);
    let centre = p.iter().copied().sum::<DVec3>() / n as f64;
    // Coordinates in the plane, scaled to the polygon's size (spade refuses magnitudes
    // below 2^-142: such a coordinate is 0 at this scale).
    let flush = |x: f64| if x.abs() < 1e-30 { 0.0 } else { x };
    let q: Vec<[f64; 2]> = p
        .iter()
        .map(|&x| {
            let d = (x - centre) / size;
            [flush(d.dot(e1)), flush(d.dot(e2))]
        })
        .collect();
    let deviation = p
        .iter()
        .map(|&x| ((x - centre) / size).dot(nz).abs())
        .fold(0.0, f64::max);
    check_simple(&q)?;
    let planar = deviation <= PLANARITY;

    let vertices: Vec<Point2<f64>> = q.iter().map(|c| Point2::new(c[0], c[1])).collect();
    let edges: Vec<[usize; 2]> = (0..n).map(|k| [k, (k + 1) % n]).collect();
    let mut conflict = false;
    let mut cdt =
        ConstrainedDelaunayTriangulation::<Point2<f64>>::try_bulk_load_cdt(vertices, edges, |_| {
            conflict = true
        })
        .map_err(|e| format!("the polygon cannot be triangulated ({e:?})"))?;
    if conflict || cdt.num_vertices() != n {
        return Err(
            "edges of the polygon cross or corners coincide (seen along its normal): \
                    it is not a simple polygon"
                .into(),
        );
    }
    let pos = |cdt: &ConstrainedDelaunayTriangulation<Point2<f64>>,
               f: FixedFaceHandle<InnerTag>| {
        cdt.face(f).vertices().map(|v| {
            let p = v.position();
            [p.x, p.y]
        })
    };
    let worst = inside_faces(&cdt)
        .into_iter()
        .map(|f| {
            let [a, b, c] = pos(&cdt, f);
            min_angle_deg(a, b, c)
        })
        .fold(f64::INFINITY, f64::min);
    if planar && worst < SLIVER_DEG {
        let area = 0.5 * normal.length() / (size * size);
        let params = RefinementParameters::<f64>::new()
            .exclude_outer_faces(true)
            .with_angle_limit(AngleLimit::from_deg(MIN_ANGLE_DEG))
            .with_min_required_area(1e-6 * area)
            .with_max_additional_vertices(8 * n + 64);
        cdt.refine(params);
    }

    // 3D positions of the added points: on the polygon's edge when on its boundary (a
    // vertex with a constraint edge), else on the best-fit plane.
    let mut extra = Vec::with_capacity(cdt.num_vertices() - n);
    let mut extra_at = Vec::with_capacity(cdt.num_vertices() - n);
    for v in cdt.vertices().skip(n) {
        let c = [v.position().x, v.position().y];
        let on_boundary = v.out_edges().any(|e| e.is_constraint_edge());
        let (point, at) = if on_boundary {
            let (k, t) = (0..n)
                .map(|k| {
                    let (d, t) = point_segment(c, q[k], q[(k + 1) % n]);
                    (d, k, t)
                })
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .map(|(_, k, t)| (k, t))
                .unwrap_or((0, 0.0));
            (p[k].lerp(p[(k + 1) % n], t), Place::Edge(k, t))
        } else {
            (centre + (e1 * c[0] + e2 * c[1]) * size, Place::Inside(c))
        };
        extra.push(point);
        extra_at.push(at);
    }
    let triangles = inside_faces(&cdt)
        .into_iter()
        .map(|f| cdt.face(f).vertices().map(|v| v.fix().index()))
        .collect();
    Ok(Meshed {
        extra,
        triangles,
        non_planar: (!planar).then_some(deviation),
        extra_at,
        plane: q,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn area(p: &[DVec3], m: &Meshed) -> f64 {
        let at = |i: usize| {
            if i < p.len() {
                p[i]
            } else {
                m.extra[i - p.len()]
            }
        };
        m.triangles
            .iter()
            .map(|t| 0.5 * (at(t[1]) - at(t[0])).cross(at(t[2]) - at(t[0])).length())
            .sum()
    }

    fn oriented(p: &[DVec3], m: &Meshed) -> bool {
        let nz = newell(p);
        let at = |i: usize| {
            if i < p.len() {
                p[i]
            } else {
                m.extra[i - p.len()]
            }
        };
        m.triangles
            .iter()
            .all(|t| (at(t[1]) - at(t[0])).cross(at(t[2]) - at(t[0])).dot(nz) > 0.0)
    }

    fn xy(c: &[(f64, f64)]) -> Vec<DVec3> {
        c.iter().map(|&(x, y)| DVec3::new(x, y, 0.0)).collect()
    }

    #[test]
    fn concave_l_keeps_its_area() {
        // Listed from a corner that does not see the whole polygon: a fan from it covers
        // the notch (16 instead of 7).
        let p = xy(&[(4., 0.), (4., 1.), (1., 1.), (1., 4.), (0., 4.), (0., 0.)]);
        let m = mesh(&p).unwrap();
        assert!((area(&p, &m) - 7.0).abs() < 1e-12, "{}", area(&p, &m));
        assert!(oriented(&p, &m));
        assert!(m.non_planar.is_none());
    }

    #[test]
    fn disk_is_refined_into_well_shaped_triangles() {
        let n = 128;
        let p: Vec<DVec3> = (0..n)
            .map(|k| {
                let t = std::f64::consts::TAU * k as f64 / n as f64;
                DVec3::new(t.cos(), 0.3, -t.sin()) // normal +y
            })
            .collect();
        let m = mesh(&p).unwrap();
        let exact = 0.5 * newell(&p).length();
        assert!(
            (area(&p, &m) - exact).abs() < 1e-13,
            "{} vs {exact}",
            area(&p, &m)
        );
        assert!(oriented(&p, &m));
        assert!(!m.extra.is_empty());
        let at = |i: usize| {
            if i < p.len() {
                p[i]
            } else {
                m.extra[i - p.len()]
            }
        };
        for t in &m.triangles {
            let q: Vec<[f64; 2]> = t.iter().map(|&i| [at(i).x, at(i).z]).collect();
            let a = min_angle_deg(q[0], q[1], q[2]);
            assert!(a >= MIN_ANGLE_DEG - 1e-6, "angle {a}");
        }
        assert!(m.triangles.len() < 4 * n, "{} triangles", m.triangles.len());
    }

    #[test]
    fn mean_value_weights_reproduce_linear_values_in_a_concave_polygon() {
        // An L (concave) and points inside it, on an edge and at a corner: the weights sum
        // to 1 and carry any affine function of the corners to the point exactly.
        let q = [[4., 0.], [4., 1.], [1., 1.], [1., 4.], [0., 4.], [0., 0.]];
        let f = |p: [f64; 2]| 0.3 + 1.7 * p[0] - 0.6 * p[1];
        for x in [
            [0.5, 0.5],
            [3.5, 0.5],
            [0.5, 3.5],
            [0.9, 0.9],
            [2.0, 1.0],
            [4.0, 1.0],
        ] {
            let w = mean_value_weights(&q, x);
            let sum: f64 = w.iter().map(|&(_, v)| v).sum();
            let value: f64 = w.iter().map(|&(i, v)| v * f(q[i])).sum();
            assert!((sum - 1.0).abs() < 1e-12, "{x:?}: {sum}");
            assert!((value - f(x)).abs() < 1e-12, "{x:?}: {value} vs {}", f(x));
        }
        // On the edge (1, 1)-(1, 4), only its two ends.
        assert_eq!(mean_value_weights(&q, [1.0, 2.5]).len(), 2);
    }

    #[test]
    fn non_planar_quad_splits_along_the_better_diagonal() {
        // A long thin quad lifted at one corner: the diagonal 1-3 is the short one.
        let p = vec![
            DVec3::new(0., 0., 0.),
            DVec3::new(4., 0., 0.),
            DVec3::new(4., 1., 0.5),
            DVec3::new(0., 1., 0.),
        ];
        let m = mesh(&p).unwrap();
        assert!(m.non_planar.is_some());
        assert!(m.extra.is_empty());
        assert_eq!(m.triangles.len(), 2);
        assert!(oriented(&p, &m));
    }

    #[test]
    fn self_intersecting_and_touching_polygons_are_refused() {
        let bowtie = xy(&[(0., 0.), (4., 1.), (4., 0.), (0., 3.)]);
        let e = mesh(&bowtie).unwrap_err();
        assert!(e.contains("self-intersecting"), "{e}");
        // A corner visited twice: two squares touching at a point.
        let touch = xy(&[
            (0., 0.),
            (1., 0.),
            (1., 1.),
            (2., 1.),
            (2., 2.),
            (1., 2.),
            (1., 1.),
            (0., 1.),
        ]);
        let e = mesh(&touch).unwrap_err();
        assert!(e.contains("not a simple polygon"), "{e}");
        // A zero-width spike.
        let spike = xy(&[(0., 0.), (1., 0.), (2., 0.), (1., 0.), (1., 1.)]);
        let e = mesh(&spike).unwrap_err();
        assert!(e.contains("not a simple polygon"), "{e}");
    }
}
