//! Patches: the scene's faces subdivided into small planar polygons.
//!
//! A patch is a handle (its index `i`, stored as `u32`) into the flat arrays of a [`PatchSet`]:
//! corners, area, normal, centroid, material, object (the pbrt-v4 layout: no object owns
//! geometry; a patch only names its scene object, by index into [`PatchSet::objects`]).
//! Quads are split into an `nu x nv` grid of quads and triangles into `n^2` similar
//! triangles, with `nu`, `nv`, `n` chosen so that no patch edge is longer than the target
//! length; a target patch count is turned into that length by a short search.
//!
//! Each face's grid is kept ([`PatchSet::grids`]: its first patch, its corners and its
//! counts), so that the visibility module can trace a planar face whole and name the
//! patch a ray hits from the hit's coordinates on the face; where there is no grid (sets
//! built elsewhere, such as the hierarchy's elements) it traces the patch triangles, and
//! a hit maps back to its patch through [`PatchSet::tri_patch`].
//!
//! Geometry is `f64` throughout (corners, normals, centroids, the f64 warp
//! [`PatchSampler::point`]); `f32` appears only where rays are made for Embree
//! ([`PatchSampler::point32`] and the visibility module).

use glam::{DVec2, DVec3, Vec3};

use crate::error::{Error, Result};
use crate::scene::{Face, Material, Scene};

/// Marks the missing 4th corner of a triangular patch.
pub const NONE: u32 = u32::MAX;

/// How finely to subdivide.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Resolution {
    /// No patch edge longer than this (scene units).
    MaxEdge(f64),
    /// About this many patches in all.
    Patches(usize),
    /// No patch edge longer than this fraction of the scene's diagonal.
    DiagonalFraction(f64),
}

/// The patches of a scene, as flat arrays indexed by patch.
#[derive(Clone, Debug, Default)]
pub struct PatchSet {
    /// Scene name, for messages and file headers.
    pub scene: String,
    /// Vertices of the patch mesh (shared within a face).
    pub vertices: Vec<DVec3>,
    /// Corner indices into `vertices`, counter-clockwise seen from the front;
    /// the 4th is [`NONE`] for triangles.
    pub corners: Vec<[u32; 4]>,
    /// Area of each patch.
    pub area: Vec<f64>,
    /// Unit normal of each patch (the side that emits and receives).
    pub normal: Vec<DVec3>,
    /// Centroid of each patch.
    pub centroid: Vec<DVec3>,
    /// Material index of each patch.
    pub material: Vec<u32>,
    /// Index of the scene face each patch came from.
    pub face: Vec<u32>,
    /// Object index of each patch (into `objects`).
    pub object: Vec<u32>,
    /// The patch on the other side of each patch of a two-sided face (the same corners
    /// wound the other way), or [`NONE`]; empty when no face is two-sided.
    pub twin: Vec<u32>,
    /// Materials (copied from the scene).
    pub materials: Vec<Material>,
    /// Object names (copied from the scene, [`Scene::objects`]).
    pub objects: Vec<String>,
    /// Patch triangles (one or two per patch), for visibility and output.
    pub triangles: Vec<[u32; 3]>,
    /// Patch of each triangle.
    pub tri_patch: Vec<u32>,
    /// Length of the diagonal of the scene's bounding box (sets ray offsets).
    pub diagonal: f64,
    /// Largest absolute coordinate of the scene: bounds the rounding of positions.
    pub magnitude: f64,
    /// The edge length the subdivision used.
    pub max_edge: f64,
    /// How each scene face was cut into patches, by face index; empty for sets not made
    /// by [`PatchSet::build`].
    pub grids: Vec<FaceGrid>,
}

/// How one scene face was cut into patches by [`PatchSet::build`]. Its patches are
/// consecutive from `first`, in the order the layout gives.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FaceGrid {
    /// The face's first patch.
    pub first: u32,
    /// The face's corners as indices into [`PatchSet::vertices`] (counter-clockwise from
    /// the front, the 4th [`NONE`] for a triangle), for [`Layout::Quad`] and
    /// [`Layout::Triangle`].
    pub corners: [u32; 4],
    /// How the patches are laid out.
    pub layout: Layout,
}

/// The patch layout of a [`FaceGrid`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Layout {
    /// Corners `p0..p3`, cut at `s = a / nu` and `t = b / nv` of the bilinear map
    /// `q(s, t) = p0 (1-s)(1-t) + p1 s (1-t) + p2 s t + p3 (1-s) t`: patch `b nu + a`
    /// is the cell `[a, a+1] / nu x [b, b+1] / nv`.
    Quad {
        /// Cells along `p0 -> p1`.
        nu: u32,
        /// Cells along `p0 -> p3`.
        nv: u32,
    },
    /// Corners `p0, p1, p2`, cut into `n²` similar triangles: with the point
    /// `p0 + (p1 - p0) x + (p2 - p0) y`, row `r = ⌊n y⌋` holds patches from `r (2n - r)`,
    /// the cell `a = ⌊n x⌋` of the row its upright triangle `2a` and the inverted one
    /// after it `2a + 1`.
    Triangle {
        /// Cuts along each side.
        n: u32,
    },
    /// The back of a two-sided face: its patches are the twins of face `front`'s, in the
    /// same order.
    Back {
        /// The face whose back this is.
        front: u32,
    },
}

/// The parameters `(s, t)` of the point `x` under the bilinear map of [`Layout::Quad`] of a
/// planar quad, written in 2D coordinates of its plane with `p0` at the origin: `x = e s +
/// f t + g s t`, `e = p1 - p0`, `f = p3 - p0`, `g = p2 - p1 - p3 + p0`. Crossing the
/// equation with `f + g s` removes `t` and leaves `(e × g) s² + (e × f - x × g) s - x × f
/// = 0` (2D cross products; Quilez, "Inverse bilinear interpolation", 2010), whose root
/// nearest the unit square is taken in the cancellation-free form; then `t` by projection
/// onto `f + g s`. Not clamped: a point outside the quad gets parameters outside `[0, 1]`
/// (non-finite ones only for a degenerate quad).
pub fn inverse_bilinear(e: DVec2, f: DVec2, g: DVec2, x: DVec2) -> (f64, f64) {
    let (a, b, c) = (e.perp_dot(g), e.perp_dot(f) - x.perp_dot(g), -x.perp_dot(f));
    let s = if a.abs() <= 1e-12 * b.abs() {
        -c / b
    } else {
        let root = (b * b - 4.0 * a * c).max(0.0).sqrt();
        let w = -0.5 * (b + root.copysign(b));
        let (r1, r2) = (w / a, c / w);
        let off = |r: f64| (r - r.clamp(0.0, 1.0)).abs();
        if off(r1) <= off(r2) || !r2.is_finite() {
            r1
        } else {
            r2
        }
    };
    let d = f + g * s;
    let t = (x - e * s).dot(d) / d.length_squared();
    (s, t)
}

impl PatchSet {
    /// Number of patches.
    pub fn len(&self) -> usize {
        self.area.len()
    }

    /// True when there are no patches.
    pub fn is_empty(&self) -> bool {
        self.area.is_empty()
    }

    /// Reflectance of patch `i`.
    pub fn rho(&self, i: usize) -> [f64; 3] {
        self.materials[self.material[i] as usize].rho
    }

    /// The patch on the other side of patch `i` ([`PatchSet::twin`]), if it has one.
    pub fn twin_of(&self, i: usize) -> Option<usize> {
        self.twin
            .get(i)
            .filter(|&&t| t != NONE)
            .map(|&t| t as usize)
    }

    /// Name of the object of patch `i`.
    pub fn object_name(&self, i: usize) -> &str {
        &self.objects[self.object[i] as usize]
    }

    /// Emission of patch `i`.
    pub fn emit(&self, i: usize) -> [f64; 3] {
        self.materials[self.material[i] as usize].emit
    }

    /// Tolerance of the geometric predicates (is a point on, in front of or behind a
    /// plane), in scene units: `1e-9` of the scene's diagonal, and never below a bound of
    /// the f64 rounding of plane distances at the scene's coordinates (`2^-40` of the
    /// largest one, about 4000 ulp). Relative to the scene, so that a scene and any
    /// scaling or rigid motion of it take the same decisions: real separations are many
    /// orders above it, coplanar points many orders below.
    pub fn plane_tol(&self) -> f64 {
        (1e-9 * self.diagonal).max(self.magnitude * f64::EPSILON * 4096.0)
    }

    /// Corner positions of patch `i` (3 or 4), read through the corner indices without
    /// gathering them into an array (for tests run on each of many pairs).
    #[inline]
    pub fn corner_iter(&self, i: usize) -> impl Iterator<Item = DVec3> + '_ {
        self.corners[i]
            .iter()
            .take_while(|&&v| v != NONE)
            .map(|&v| self.vertices[v as usize])
    }

    /// Corner positions of patch `i` (3 or 4).
    pub fn corner_points(&self, i: usize) -> ([DVec3; 4], usize) {
        let mut p = [DVec3::ZERO; 4];
        let mut n = 0;
        for (slot, q) in p.iter_mut().zip(self.corner_iter(i)) {
            *slot = q;
            n += 1;
        }
        (p, n)
    }

    /// Maps `(u, v)` in the unit square to a point of patch `i`, uniformly by area:
    /// triangles by the square-root warp (Shirley and Chiu 1997; pbrt-v4
    /// `SampleUniformTriangle`), parallelograms bilinearly, other quads by picking one of
    /// their two triangles with probability proportional to its area (on `u`).
    /// For many points on one patch, [`PatchSet::sampler`] does the per-patch work once.
    #[inline]
    pub fn sample_point(&self, i: usize, u: f64, v: f64) -> DVec3 {
        self.sampler(i).point(u, v)
    }

    /// The warp of [`PatchSet::sample_point`] for patch `i`, with its per-patch set-up
    /// (corner loads, parallelogram test, triangle areas) done once.
    #[inline]
    pub fn sampler(&self, i: usize) -> PatchSampler {
        let (p, n) = self.corner_points(i);
        PatchSampler::of_corners(p, n)
    }

    /// Builds the patches of `scene` at the given resolution, checked by
    /// [`PatchSet::validate`].
    pub fn build(scene: &Scene, res: Resolution) -> Result<PatchSet> {
        let (lo, hi) = scene.bounds();
        let diagonal = (hi - lo).length();
        let magnitude = lo.abs().max(hi.abs()).max_element();
        if diagonal.is_nan() || diagonal <= 0.0 || !diagonal.is_finite() {
            return Err(Error::Scene {
                scene: scene.source.clone(),
                msg: "the scene has no extent (all vertices coincide)".into(),
            });
        }
        let max_edge = match res {
            Resolution::MaxEdge(h) if h > 0.0 && h.is_finite() => h,
            Resolution::MaxEdge(h) => {
                return Err(Error::Config(format!(
                    "patch edge length must be > 0, got {h}"
                )))
            }
            Resolution::Patches(0) => {
                return Err(Error::Config("patch count must be at least 1".into()))
            }
            Resolution::Patches(n) => edge_for_count(scene, n),
            Resolution::DiagonalFraction(f) if f > 0.0 && f.is_finite() => f * diagonal,
            Resolution::DiagonalFraction(f) => {
                return Err(Error::Config(format!(
                    "patch edge fraction must be > 0, got {f}"
                )))
            }
        };
        let mut set = PatchSet {
            scene: scene.name.clone(),
            materials: scene.materials.clone(),
            objects: scene.objects.clone(),
            diagonal,
            magnitude,
            max_edge,
            ..Default::default()
        };
        // Patches of each face, so that the back of a two-sided face copies its front's.
        let mut range = Vec::with_capacity(scene.faces.len());
        for (fi, face) in scene.faces.iter().enumerate() {
            let start = set.len();
            let layout = match range.get(face.twin as usize) {
                Some(&(a, b)) if face.back => {
                    // Corner 0 is the same corner on both sides; a side raised off a face
                    // it lay on (`Scene::raise_coincident`) is that far off the other.
                    let front = &scene.faces[face.twin as usize];
                    let shift = scene.positions[face.corners[0] as usize]
                        - scene.positions[front.corners[0] as usize];
                    set.add_back(a..b, face, fi as u32, shift);
                    Layout::Back { front: face.twin }
                }
                _ => set.add_face(scene, fi as u32, face, max_edge),
            };
            range.push((start, set.len()));
            let c = |k: usize| set.corners[k];
            let corners = match layout {
                Layout::Quad { nu, nv } => {
                    let (nu, nv) = (nu as usize, nv as usize);
                    [
                        c(start)[0],
                        c(start + nu - 1)[1],
                        c(start + nu * nv - 1)[2],
                        c(start + nu * (nv - 1))[3],
                    ]
                }
                Layout::Triangle { n } => {
                    let n = n as usize;
                    [
                        c(start)[0],
                        c(start + 2 * (n - 1))[1],
                        c(start + n * n - 1)[2],
                        NONE,
                    ]
                }
                Layout::Back { .. } => [NONE; 4],
            };
            set.grids.push(FaceGrid {
                first: start as u32,
                corners,
                layout,
            });
        }
        if !set.twin.is_empty() {
            set.twin.resize(set.len(), NONE);
        }
        if set.len() > (u32::MAX / 4) as usize {
            return Err(Error::Config(format!("{} patches are too many", set.len())));
        }
        set.validate()?;
        Ok(set)
    }

    fn add_face(&mut self, scene: &Scene, fi: u32, face: &Face, h: f64) -> Layout {
        let p: Vec<DVec3> = face
            .corner_slice()
            .iter()
            .map(|&c| scene.positions[c as usize])
            .collect();
        let base = self.vertices.len() as u32;
        if p.len() == 4 {
            let nu = cells(p[1] - p[0], h).max(cells(p[2] - p[3], h));
            let nv = cells(p[3] - p[0], h).max(cells(p[2] - p[1], h));
            for b in 0..=nv {
                let t = b as f64 / nv as f64;
                for a in 0..=nu {
                    let s = a as f64 / nu as f64;
                    let q = p[0] * ((1.0 - s) * (1.0 - t))
                        + p[1] * (s * (1.0 - t))
                        + p[2] * (s * t)
                        + p[3] * ((1.0 - s) * t);
                    self.vertices.push(q);
                }
            }
            let at = |a: usize, b: usize| base + (b * (nu + 1) + a) as u32;
            for b in 0..nv {
                for a in 0..nu {
                    let c = [at(a, b), at(a + 1, b), at(a + 1, b + 1), at(a, b + 1)];
                    self.push_patch(c, face, fi);
                }
            }
            Layout::Quad {
                nu: nu as u32,
                nv: nv as u32,
            }
        } else {
            let n = cells(p[1] - p[0], h)
                .max(cells(p[2] - p[1], h))
                .max(cells(p[0] - p[2], h));
            // Row r has n - r + 1 vertices: P = p0 + (p1 - p0) a/n + (p2 - p0) r/n.
            let mut row_start = Vec::with_capacity(n + 1);
            for r in 0..=n {
                row_start.push(self.vertices.len() as u32);
                for a in 0..=(n - r) {
                    let q = p[0]
                        + (p[1] - p[0]) * (a as f64 / n as f64)
                        + (p[2] - p[0]) * (r as f64 / n as f64);
                    self.vertices.push(q);
                }
            }
            for r in 0..n {
                for a in 0..(n - r) {
                    let (v0, v1) = (row_start[r] + a as u32, row_start[r] + a as u32 + 1);
                    let v2 = row_start[r + 1] + a as u32;
                    self.push_patch([v0, v1, v2, NONE], face, fi);
                    if a + 1 < n - r {
                        let v3 = row_start[r + 1] + a as u32 + 1;
                        self.push_patch([v1, v3, v2, NONE], face, fi);
                    }
                }
            }
            Layout::Triangle { n: n as u32 }
        }
    }

    /// The back of a two-sided face: a copy of the patches `front` (its twin's) with their
    /// corners wound the other way (corner 0 first), on vertices of its own moved by
    /// `shift`, so each back patch lies exactly on its front patch (`shift` zero, unless
    /// one side was raised off a face it lay on) and its triangles on the front's triangles
    /// (the same diagonal). Front and back are each other's [`PatchSet::twin`].
    fn add_back(&mut self, front: std::ops::Range<usize>, face: &Face, fi: u32, shift: DVec3) {
        if self.twin.len() < self.len() {
            self.twin.resize(self.len(), NONE);
        }
        let mut copy: std::collections::HashMap<u32, u32> = std::collections::HashMap::new();
        for p in front {
            let c = self.corners[p];
            let mut v = |k: u32| -> u32 {
                *copy.entry(k).or_insert_with(|| {
                    self.vertices.push(self.vertices[k as usize] + shift);
                    (self.vertices.len() - 1) as u32
                })
            };
            let back = if c[3] == NONE {
                [v(c[0]), v(c[2]), v(c[1]), NONE]
            } else {
                [v(c[0]), v(c[3]), v(c[2]), v(c[1])]
            };
            let id = self.len();
            self.push_patch(back, face, fi);
            self.twin.resize(self.len(), NONE);
            self.twin[id] = p as u32;
            self.twin[p] = id as u32;
        }
    }

    fn push_patch(&mut self, c: [u32; 4], from: &Face, face: u32) {
        let n = if c[3] == NONE { 3 } else { 4 };
        let pts: Vec<DVec3> = c[..n].iter().map(|&k| self.vertices[k as usize]).collect();
        let mut newell = DVec3::ZERO;
        let mut centroid = DVec3::ZERO;
        let mut area_sum = 0.0;
        for k in 1..n - 1 {
            let cr = (pts[k] - pts[0]).cross(pts[k + 1] - pts[0]);
            newell += cr;
            let a = cr.length() * 0.5;
            centroid += (pts[0] + pts[k] + pts[k + 1]) / 3.0 * a;
            area_sum += a;
        }
        let id = self.area.len() as u32;
        self.corners.push(c);
        self.area.push(newell.length() * 0.5);
        self.normal.push(newell.normalize_or_zero());
        self.centroid
            .push(centroid / area_sum.max(f64::MIN_POSITIVE));
        self.material.push(from.material);
        self.object.push(from.object);
        self.face.push(face);
        self.triangles.push([c[0], c[1], c[2]]);
        self.tri_patch.push(id);
        if n == 4 {
            self.triangles.push([c[0], c[2], c[3]]);
            self.tri_patch.push(id);
        }
    }

    /// Checks every patch for finite, non-degenerate geometry; names the first bad patch.
    pub fn validate(&self) -> Result<()> {
        for i in 0..self.len() {
            let a = self.area[i];
            if !a.is_finite() || a <= 0.0 || !self.normal[i].is_finite() {
                return Err(Error::Scene {
                    scene: self.scene.clone(),
                    msg: format!(
                        "patch {i} (face {}) is degenerate: area {a:e}, normal {:?}",
                        self.face[i], self.normal[i]
                    ),
                });
            }
        }
        Ok(())
    }
}

/// Number of segments of length at most `h` along `edge`.
fn cells(edge: DVec3, h: f64) -> usize {
    ((edge.length() / h).ceil() as usize).clamp(1, 1 << 16)
}

/// How a [`PatchSampler`] maps the unit square onto its patch.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Warp {
    Triangle,
    Parallelogram,
    /// A general quad: triangle (0, 1, 2) with this probability, else (0, 2, 3).
    TwoTriangles(f64),
}

/// Uniform points on one patch (see [`PatchSet::sample_point`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PatchSampler {
    p: [DVec3; 4],
    kind: Warp,
    /// Set-up of [`PatchSampler::point32`]: the first corner, the edge vectors `e1`, `e2` of
    /// the first triangle (`a + sqrt(u) e1 + sqrt(u) v e2`) or of the parallelogram
    /// (`a + u e1 + v e2`), for a general quad the differences between the second
    /// triangle's edges and the first's, the split `w` of `u` between the two triangles, and
    /// the scale that maps the first part of `u` back to [0, 1] with its difference from the
    /// second part's (all in f32, rounded from f64).
    a: Vec3,
    e: [Vec3; 4],
    w: f32,
    scale: f32,
    dscale: f32,
}

impl PatchSampler {
    /// The sampler of a patch with these corners (`n` = 3 or 4 of them, as
    /// [`PatchSet::corner_points`] returns them).
    pub fn of_corners(p: [DVec3; 4], n: usize) -> PatchSampler {
        if n == 3 {
            return PatchSampler::new(p, Warp::Triangle);
        }
        let skew = p[0] + p[2] - p[1] - p[3];
        if skew.length_squared() <= 1e-12 * (p[2] - p[0]).length_squared() {
            return PatchSampler::new(p, Warp::Parallelogram);
        }
        let a1 = (p[1] - p[0]).cross(p[2] - p[0]).length();
        let a2 = (p[2] - p[0]).cross(p[3] - p[0]).length();
        PatchSampler::new(p, Warp::TwoTriangles(a1 / (a1 + a2)))
    }

    fn new(p: [DVec3; 4], kind: Warp) -> PatchSampler {
        let (e, w) = match kind {
            Warp::Triangle => ([p[1] - p[0], p[2] - p[1], DVec3::ZERO, DVec3::ZERO], 1.0),
            Warp::Parallelogram => ([p[1] - p[0], p[3] - p[0], DVec3::ZERO, DVec3::ZERO], 1.0),
            Warp::TwoTriangles(w) => (
                // The second triangle's edges as differences from the first's.
                [
                    p[1] - p[0],
                    p[2] - p[1],
                    (p[2] - p[0]) - (p[1] - p[0]),
                    (p[3] - p[2]) - (p[2] - p[1]),
                ],
                w as f32,
            ),
        };
        PatchSampler {
            p,
            kind,
            a: p[0].as_vec3(),
            e: e.map(|v| v.as_vec3()),
            w,
            scale: 1.0 / w,
            dscale: if w < 1.0 {
                1.0 / (1.0 - w) - 1.0 / w
            } else {
                0.0
            },
        }
    }

    /// The point of `(u, v)` in the unit square.
    #[inline]
    pub fn point(&self, u: f64, v: f64) -> DVec3 {
        let p = &self.p;
        match self.kind {
            Warp::Triangle => sample_triangle(p[0], p[1], p[2], u, v),
            Warp::Parallelogram => p[0] + (p[1] - p[0]) * u + (p[3] - p[0]) * v,
            Warp::TwoTriangles(w) => {
                if u < w {
                    sample_triangle(p[0], p[1], p[2], u / w, v)
                } else {
                    sample_triangle(p[0], p[2], p[3], ((u - w) / (1.0 - w)).min(1.0), v)
                }
            }
        }
    }

    /// The same warp as [`PatchSampler::point`] in `f32`, without branches on `(u, v)`
    /// (the triangle of a general quad is selected, not branched to), for the inner loops
    /// of the area estimators.
    #[inline(always)]
    pub fn point32(&self, u: f32, v: f32) -> Vec3 {
        let (a, e) = (self.a, &self.e);
        match self.kind {
            Warp::Parallelogram => a + e[0] * u + e[1] * v,
            Warp::Triangle => {
                let su = u.sqrt();
                a + e[0] * su + e[1] * (su * v)
            }
            Warp::TwoTriangles(_) => {
                let w = self.w;
                // The triangle is picked arithmetically (f = 0 or 1), not by a branch the
                // predictor would miss half the time (LLVM turns selects into branches).
                let f = (u >= w) as u32 as f32;
                let su = ((u - f * w) * (self.scale + f * self.dscale))
                    .min(1.0)
                    .sqrt();
                a + (e[0] + e[2] * f) * su + (e[1] + e[3] * f) * (su * v)
            }
        }
    }

    /// [`PatchSampler::point32`] of every `(u[k], v[k])`, into `out = [x, y, z]` (at least
    /// as long as `u`): one loop per warp, without branches inside, so the compiler
    /// runs it four points at a time.
    #[inline(always)]
    pub fn points32(&self, u: &[f32], v: &[f32], out: &mut [Vec<f32>; 3]) {
        let len = u.len();
        let v = &v[..len];
        let [x, y, z] = out;
        let (x, y, z) = (&mut x[..len], &mut y[..len], &mut z[..len]);
        let (a, e) = (self.a, self.e);
        match self.kind {
            Warp::Parallelogram => {
                for k in 0..len {
                    let (u, v) = (u[k], v[k]);
                    x[k] = a.x + e[0].x * u + e[1].x * v;
                    y[k] = a.y + e[0].y * u + e[1].y * v;
                    z[k] = a.z + e[0].z * u + e[1].z * v;
                }
            }
            Warp::Triangle => {
                for k in 0..len {
                    let su = u[k].sqrt();
                    let sv = su * v[k];
                    x[k] = a.x + e[0].x * su + e[1].x * sv;
                    y[k] = a.y + e[0].y * su + e[1].y * sv;
                    z[k] = a.z + e[0].z * su + e[1].z * sv;
                }
            }
            Warp::TwoTriangles(_) => {
                let (w, scale, dscale) = (self.w, self.scale, self.dscale);
                for k in 0..len {
                    let f = (u[k] >= w) as u32 as f32;
                    let su = ((u[k] - f * w) * (scale + f * dscale)).min(1.0).sqrt();
                    let sv = su * v[k];
                    x[k] = a.x + (e[0].x + e[2].x * f) * su + (e[1].x + e[3].x * f) * sv;
                    y[k] = a.y + (e[0].y + e[2].y * f) * su + (e[1].y + e[3].y * f) * sv;
                    z[k] = a.z + (e[0].z + e[2].z * f) * su + (e[1].z + e[3].z * f) * sv;
                }
            }
        }
    }
}

/// Uniform point on triangle (a, b, c) from (u, v) in the unit square.
#[inline]
fn sample_triangle(a: DVec3, b: DVec3, c: DVec3, u: f64, v: f64) -> DVec3 {
    let su = u.sqrt();
    let (b0, b1) = (1.0 - su, v * su);
    a * b0 + b * (1.0 - b0 - b1) + c * b1
}

/// The number of patches [`PatchSet::build`] makes from `scene` with edge length `h`,
/// without making them.
pub fn patch_count(scene: &Scene, h: f64) -> usize {
    scene
        .faces
        .iter()
        .map(|f| {
            let p: Vec<DVec3> = f
                .corner_slice()
                .iter()
                .map(|&c| scene.positions[c as usize])
                .collect();
            if p.len() == 4 {
                cells(p[1] - p[0], h)
                    .max(cells(p[2] - p[3], h))
                    .saturating_mul(cells(p[3] - p[0], h).max(cells(p[2] - p[1], h)))
            } else {
                let k = cells(p[1] - p[0], h)
                    .max(cells(p[2] - p[1], h))
                    .max(cells(p[0] - p[2], h));
                k.saturating_mul(k)
            }
        })
        .fold(0usize, usize::saturating_add)
}

/// About how many patches `res` gives for `scene` (exact for [`Resolution::MaxEdge`]).
pub fn expected_patches(scene: &Scene, res: Resolution) -> usize {
    match res {
        Resolution::MaxEdge(h) if h > 0.0 && h.is_finite() => patch_count(scene, h),
        Resolution::MaxEdge(_) => 0,
        Resolution::Patches(n) => n,
        Resolution::DiagonalFraction(f) if f > 0.0 && f.is_finite() => {
            let (lo, hi) = scene.bounds();
            patch_count(scene, f * (hi - lo).length())
        }
        Resolution::DiagonalFraction(_) => 0,
    }
}

/// Finds the edge length that gives about `n` patches (within a few percent).
fn edge_for_count(scene: &Scene, n: usize) -> f64 {
    let count = |h: f64| patch_count(scene, h);
    // The count falls as h grows: bisect on log h between "one patch per face" and tiny.
    let (lo0, hi0) = scene.bounds();
    let mut hi = (hi0 - lo0).length() * 2.0;
    let mut lo = hi * 1e-5;
    for _ in 0..60 {
        let mid = (lo * hi).sqrt();
        if count(mid) > n {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    hi
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The inverse bilinear map undoes the bilinear one on a trapezoid and on a kite.
    #[test]
    fn inverse_bilinear_undoes_the_map() {
        for q in [
            [
                DVec2::new(2.0, 0.0),
                DVec2::new(1.5, 1.0),
                DVec2::new(0.5, 1.0),
            ],
            [
                DVec2::new(1.0, -0.2),
                DVec2::new(1.7, 1.1),
                DVec2::new(0.1, 0.9),
            ],
        ] {
            let (e, f) = (q[0], q[2]);
            for k in 0..121 {
                let (s, t) = (0.1 * (k % 11) as f64, 0.1 * (k / 11) as f64);
                let x = q[0] * (s * (1.0 - t)) + q[1] * (s * t) + q[2] * ((1.0 - s) * t);
                let (s2, t2) = inverse_bilinear(e, f, q[1] - e - f, x);
                assert!(
                    (s2 - s).abs() < 1e-12 && (t2 - t).abs() < 1e-12,
                    "{s} {t}: {s2} {t2}"
                );
            }
        }
    }
    use crate::scene::builtin;

    #[test]
    fn areas_add_up() {
        let scene = builtin::load("cornell").unwrap().unwrap();
        let coarse = PatchSet::build(&scene, Resolution::MaxEdge(1e4)).unwrap();
        let fine = PatchSet::build(&scene, Resolution::MaxEdge(40.0)).unwrap();
        let (a, b): (f64, f64) = (coarse.area.iter().sum(), fine.area.iter().sum());
        assert!((a - b).abs() < 1e-6 * a, "{a} vs {b}");
        assert!(fine.len() > 500);
        fine.validate().unwrap();
    }

    #[test]
    fn f32_warp_matches_the_f64_warp() {
        // The Cornell walls are slightly non-planar quads (two-triangle warp); the plates
        // are parallelograms; a triangle face covers the third warp.
        let cornell = builtin::load("cornell").unwrap().unwrap();
        let mut tri = builtin::load("plates-parallel").unwrap().unwrap();
        let f = tri.faces[0];
        tri.faces[0].corners = [f.corners[0], f.corners[1], f.corners[2], NONE];
        let mut kinds = Vec::new();
        for scene in [&cornell, &tri] {
            let set = PatchSet::build(scene, Resolution::MaxEdge(1e4)).unwrap();
            for i in 0..set.len() {
                let s = set.sampler(i);
                kinds.push(std::mem::discriminant(&s.kind));
                let scale = set.diagonal as f32;
                let uv = [(0.0, 0.0), (0.3, 0.9), (0.7, 0.2), (0.999, 0.5), (0.5, 0.0)];
                let (us, vs): (Vec<f32>, Vec<f32>) = uv.iter().copied().unzip();
                let mut out = [vec![0.0; 5], vec![0.0; 5], vec![0.0; 5]];
                s.points32(&us, &vs, &mut out);
                for (k, &(u, v)) in uv.iter().enumerate() {
                    let (a, b) = (s.point(u as f64, v as f64).as_vec3(), s.point32(u, v));
                    let c = Vec3::new(out[0][k], out[1][k], out[2][k]);
                    assert!(
                        (a - b).length() <= 1e-6 * scale,
                        "patch {i} ({u}, {v}): {a} vs {b}"
                    );
                    assert!(
                        (a - c).length() <= 1e-6 * scale,
                        "patch {i} ({u}, {v}): {a} vs {c}"
                    );
                }
            }
        }
        kinds.sort_by_key(|k| format!("{k:?}"));
        kinds.dedup();
        assert_eq!(kinds.len(), 3, "all three warps exercised");
    }

    #[test]
    fn patch_count_target_is_close() {
        let scene = builtin::load("cornell").unwrap().unwrap();
        let set = PatchSet::build(&scene, Resolution::Patches(1000)).unwrap();
        assert!((900..=1100).contains(&set.len()), "{}", set.len());
    }

    #[test]
    fn triangle_subdivision_covers_area() {
        let mut scene = builtin::load("plates-parallel").unwrap().unwrap();
        scene.faces.truncate(1);
        let f = scene.faces[0];
        scene.faces[0].corners = [f.corners[0], f.corners[1], f.corners[2], NONE];
        let set = PatchSet::build(&scene, Resolution::MaxEdge(0.2)).unwrap();
        let total: f64 = set.area.iter().sum();
        assert!((total - 0.5).abs() < 1e-6);
        assert_eq!(set.len(), 64); // n = ceil(sqrt(2) / 0.2) = 8 -> 64 triangles
    }
}
