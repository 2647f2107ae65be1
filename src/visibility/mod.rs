//! Visibility queries between points of the scene, hiding the ray tracer behind them.
//!
//! Estimators ask two questions, through the [`Tracer`] trait over named
//! structure-of-arrays batches ([`Segments`], [`Rays`]): is the segment between two
//! surface points free, and what does a ray from a surface point hit first.
//! [`Visibility`] answers them over Embree (also one ray at a time,
//! [`Visibility::first_hit`], and for arrays of [`SegmentRay`]s,
//! [`Visibility::segments_visible`]); the benchmark's recorder answers them with a stub.
//!
//! Geometry arrives in `f64`; this module is where it becomes `f32` for Embree (the
//! vertex buffer, ray origins and directions). The offset policy lives here, in one place
//! ([`Offsets`]): each end of a segment is moved off its surface along its own normal,
//! toward the side the ray leaves or arrives from, by `eps` = 1e-5 of the scene diagonal,
//! but never by more than a quarter of the far end's distance from the near end's plane
//! (so that two surfaces closer than `eps` keep both ends between them) nor less than
//! `floor`, a few `f32` rounding units at the scene's largest coordinate (so that an end
//! rounded to `f32` stays off its surface); and the ray stops short of the far end (pbrt-v4
//! `SpawnRayTo`; Embree does not promise what happens for hits exactly at
//! `tnear`/`tfar`), and starts a millionth of its length past its origin: an origin drawn
//! within `f32` rounding of a concave edge, offset off its own face, can round onto the
//! face across the edge, which Embree reports hit at `t = 0` (at most `1e-6` of the
//! diagonal, a tenth of `eps`, is skipped). Because both ends sit on the front side of their patches, a segment
//! never hits its own patches, and a point in a corner cannot leak through the wall it
//! touches. An end closer than `floor` to the *other* end's plane (a point on the edge
//! that its face shares with the other's) is also moved off that plane, to `floor`:
//! rounded onto it, the segment would run inside the other face and hit it. Both bounds scale with the scene, so a scaled copy casts the same rays, scaled.
//! Closest-hit rays leave from `eps` off their surface and count hits from `floor` on (for
//! the same reason: an origin rounded onto the face across a concave edge).
//!
//! What Embree holds is the scene's faces, not its patches: a planar face of the patch
//! set's grids ([`crate::mesh::FaceGrid`]) goes in whole, as its own one or two
//! triangles, and a hit names its patch by where it falls on the face (the grid cell of
//! its barycentric coordinates). The patch triangles tile such a face exactly, so both
//! scenes give the same answers up to the `f32` rounding of their vertices (a ray within
//! that rounding of a patch edge may go to either neighbour, in either scene); a quad off
//! its plane by more than `1e-3` of `eps`, and every patch of a set without grids (the
//! hierarchy's elements), go in by their patch triangles. On the Cornell box at 299,681
//! patches, Embree's closest-hit queries over the faces took 0.42-0.44 of the time they
//! took over the patch triangles (`docs/PERFORMANCE.md`, section 1).

mod embree;

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Instant;

use glam::{DVec2, DVec3, Vec3};

use crate::error::Result;
use crate::mesh::{inverse_bilinear, Layout, PatchSet, NONE};

pub use embree::flush_denormals;
pub use embree::PacketWidth;
pub(crate) use embree::{EmbreeScene, HitPacket16, SegmentPacket16};

/// Relative offset of ray ends from their surfaces, as a fraction of the scene diagonal.
pub const OFFSET_REL: f32 = 1e-5;

/// `tfar` of a segment ray: it stops this fraction of its length short of the far end.
pub const SEGMENT_TFAR: f32 = 1.0 - 1e-4;

/// `tnear` of a segment ray: it starts this fraction of its length past its origin
/// (module docs), at most 0.1 of the offset `eps` in scene units.
pub const SEGMENT_TNEAR: f32 = 1e-6;

/// The ray-offset policy of the module docs, for a scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Offsets {
    /// Offset of ray ends off their surfaces (scene units): `OFFSET_REL` of the diagonal.
    pub eps: f32,
    /// Least offset: 2 `f32` ulps of the largest coordinate of the scene.
    pub floor: f32,
}

impl Offsets {
    /// The offsets for `patches`.
    pub fn of(patches: &PatchSet) -> Offsets {
        let floor = (2.0 * f64::from(f32::EPSILON) * patches.magnitude) as f32;
        let eps = (patches.diagonal as f32 * OFFSET_REL).max(floor);
        Offsets {
            eps: eps.max(f32::MIN_POSITIVE),
            floor: floor.max(f32::MIN_POSITIVE),
        }
    }

    /// Offsets `(along n_x, along n_y)` of the two ends of the segment from `x` to `y`,
    /// given `cos_x = |n_x · (y - x)|` and `cos_y = |n_y · (y - x)|` (unnormalised: the
    /// distances of each end from the other's plane).
    #[inline(always)]
    pub fn ends(&self, cos_x: f32, cos_y: f32) -> (f32, f32) {
        (
            (0.25 * cos_y).min(self.eps).max(self.floor),
            (0.25 * cos_x).min(self.eps).max(self.floor),
        )
    }
}

/// A segment ray `(origin, direction, tfar)` with tnear = [`SEGMENT_TNEAR`], as made by
/// [`Visibility::segment_ray`].
pub type SegmentRay = (Vec3, Vec3, f32);

/// Rays as structure of arrays, the layout of Embree's packets: ray k leaves `(org[0][k],
/// org[1][k], org[2][k])` along `dir[.][k]`. For closest-hit queries the origins are
/// already offset (see [`Visibility::first_hit_origin`]) and the directions have unit
/// length; [`Segments`] use them with directions that reach the far end.
#[derive(Clone, Copy, Debug)]
pub struct Rays<'a> {
    /// Origins, by coordinate.
    pub org: [&'a [f32]; 3],
    /// Directions, by coordinate.
    pub dir: [&'a [f32]; 3],
}

impl<'a> Rays<'a> {
    /// The rays in runs of 16 (the last one shorter), as the slices an Embree packet copies:
    /// `(origins, directions)` by coordinate.
    #[inline(always)]
    pub fn packets16(&self) -> impl Iterator<Item = ([&'a [f32]; 3], [&'a [f32]; 3])> + '_ {
        let (o, d) = (self.org, self.dir);
        (0..self.len()).step_by(16).map(move |lo| {
            let hi = (lo + 16).min(self.len());
            (
                [&o[0][lo..hi], &o[1][lo..hi], &o[2][lo..hi]],
                [&d[0][lo..hi], &d[1][lo..hi], &d[2][lo..hi]],
            )
        })
    }

    /// Number of rays.
    pub fn len(&self) -> usize {
        self.org[0].len()
    }

    /// True when there is no ray.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Ray k as a [`Ray`].
    pub fn ray(&self, k: usize) -> Ray {
        let (o, d) = (self.org, self.dir);
        (
            Vec3::new(o[0][k], o[1][k], o[2][k]),
            Vec3::new(d[0][k], d[1][k], d[2][k]),
        )
    }
}

/// Segment rays as structure of arrays: [`Rays`] whose directions run from the origin to
/// the far end (offsets applied as in [`Visibility::segment_ray`], so not unit), each over
/// `t` in `[SEGMENT_TNEAR, tfar]`. This is the layout of Embree's packets, so a batch goes to
/// `rtcOccluded16` without being transposed.
#[derive(Clone, Copy, Debug)]
pub struct Segments<'a> {
    /// Origins and directions.
    pub rays: Rays<'a>,
    /// Common end of every ray, in units of its direction.
    pub tfar: f32,
}

impl Segments<'_> {
    /// Number of rays.
    pub fn len(&self) -> usize {
        self.rays.len()
    }

    /// True when there is no ray.
    pub fn is_empty(&self) -> bool {
        self.rays.is_empty()
    }

    /// Ray k as a [`SegmentRay`].
    pub fn ray(&self, k: usize) -> SegmentRay {
        let (o, d) = self.rays.ray(k);
        (o, d, self.tfar)
    }
}

/// A ray `(origin, unit direction)` for closest-hit queries.
pub type Ray = (Vec3, Vec3);

/// The narrow interface between the estimators and the ray tracer: the two batched
/// queries they make, over named structure-of-arrays ray batches. [`Visibility`]
/// implements it over Embree; the benchmark implements it as a recorder of the rays asked
/// for. The rays an estimator asks for never depend on the answers.
pub trait Tracer {
    /// `out[k]` is true when nothing blocks segment k (as made by
    /// [`Visibility::segment_ray`] or the same [`Offsets`] policy).
    fn segments_visible(&self, segs: &Segments, out: &mut [bool]);
    /// `out[k]` is the patch whose front side ray k meets first, or [`NO_HIT`] (origins
    /// already offset, as by [`Visibility::first_hit_origin`]).
    fn first_front_hits(&self, rays: &Rays, out: &mut [u32]);
}

impl Tracer for Visibility {
    #[inline]
    fn segments_visible(&self, segs: &Segments, out: &mut [bool]) {
        if self.timing.load(Ordering::Relaxed) {
            self.timed(|| self.segments_visible_soa(segs, out))
        } else {
            self.segments_visible_soa(segs, out)
        }
    }

    #[inline]
    fn first_front_hits(&self, rays: &Rays, out: &mut [u32]) {
        if self.timing.load(Ordering::Relaxed) {
            self.timed(|| self.first_front_hits_soa(rays, out))
        } else {
            self.first_front_hits_soa(rays, out)
        }
    }
}

/// The patch id [`Visibility::first_front_hits_soa`] reports for a ray that hits nothing.
pub const NO_HIT: u32 = u32::MAX;

/// What a ray hit first.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// The patch hit.
    pub patch: u32,
    /// Distance along the (unit) direction.
    pub t: f32,
}

/// Visibility queries over the faces of a [`PatchSet`]: each planar face of its
/// [`PatchSet::grids`] traced whole (one or two triangles; see the module docs), every
/// other face by its patch triangles.
pub struct Visibility {
    scene: EmbreeScene,
    /// For each traced triangle: the patch it belongs to, or with [`WHOLE`] set the face
    /// it is half of; with [`ALONG`] set when its winding normal points to the patch's (or
    /// face's) front side ([`Visibility::first_front_hits_soa`]).
    tri_front: Vec<u32>,
    /// For each patch triangle, the patch a ray meeting its back reaches: the twin of its
    /// patch (the other side of a two-sided face, lying on it) or [`NO_HIT`].
    tri_back: Vec<u32>,
    /// The faces traced whole.
    wholes: Vec<Whole>,
    offsets: Offsets,
    /// Whether to time the Embree calls ([`Visibility::time_queries`]), and the
    /// nanoseconds spent inside them so far, summed over threads.
    timing: AtomicBool,
    query_nanos: AtomicU64,
}

/// Fewest segment rays traced as one `rtcOccluded16` packet where 16-wide packets are
/// native (AVX-512); shorter runs go one `rtcOccluded1` each. A coherent full packet ran at 1.7 to 2.2 times the single-ray rate
/// (`docs/PERFORMANCE.md`, section 2), so a packet costs about 8 single rays: the
/// semi-analytic estimator's batches of 4 rays per node (before it traced a pair's nodes
/// as one batch) ran its stage at about 0.23 of the raw loop as packets against 0.25-0.26
/// as single rays (400-patch Cornell box, shared machine).
pub const PACKET_MIN: usize = 8;

/// Bit of [`Visibility`]'s `tri_front` entries: winding normal along the patch normal.
const ALONG: u32 = 1 << 31;

/// Bit of [`Visibility`]'s `tri_front` entries: the triangle is half `h` of the face traced
/// whole `w` ([`Whole`]), and the bits below this one hold `2 w + h`.
const WHOLE: u32 = 1 << 30;

impl Visibility {
    /// Builds the acceleration structure: over the faces of `patches.grids` that are
    /// planar, traced whole, and over the patch triangles of the others (or of every patch,
    /// when the set has no grids).
    pub fn new(patches: &PatchSet) -> Result<Visibility> {
        if patches.len() >= WHOLE as usize {
            return Err(crate::error::Error::Embree(format!(
                "{} patches are too many to trace (at most {})",
                patches.len(),
                WHOLE - 1
            )));
        }
        let offsets = Offsets::of(patches);
        let t = Traced::of(patches, offsets);
        let v32: Vec<Vec3> = patches.vertices.iter().map(|v| v.as_vec3()).collect();
        let scene = EmbreeScene::new(&v32, &t.triangles)?;
        Ok(Visibility {
            scene,
            tri_front: t.front,
            tri_back: t.back,
            wholes: t.wholes,
            offsets,
            timing: AtomicBool::new(false),
            query_nanos: AtomicU64::new(0),
        })
    }

    /// Number of triangles in the acceleration structure.
    pub fn traced_triangles(&self) -> usize {
        self.tri_front.len()
    }

    /// Number of faces traced whole (see the module docs).
    pub fn whole_faces(&self) -> usize {
        self.wholes.len()
    }

    /// The patch on the front side of the point with barycentrics `(u, v)` of traced
    /// triangle `prim`, the patch on its back side ([`NO_HIT`] when the face is one-sided),
    /// and whether the triangle's winding normal points to the front.
    #[inline(always)]
    fn sides(&self, prim: u32, u: f32, v: f32) -> (u32, u32, bool) {
        let t = self.tri_front[prim as usize];
        let along = t & ALONG != 0;
        if t & WHOLE == 0 {
            return (t & !ALONG, self.tri_back[prim as usize], along);
        }
        let k = t & !(ALONG | WHOLE);
        let w = &self.wholes[(k >> 1) as usize];
        let cell = w.cut.cell(k & 1, f64::from(u), f64::from(v));
        let back = if w.back == NO_HIT {
            NO_HIT
        } else {
            w.back + cell
        };
        (w.first + cell, back, along)
    }

    /// Starts (or stops) timing the estimators' batches of queries ([`Tracer`]'s two
    /// calls: Embree's packet and single-ray calls with the copies into and out of its
    /// packets, about 1 ns a ray against Embree's 25 to 90), and resets the total. The
    /// clock is read around each batch, not each packet: timing every packet inside the
    /// SIMD-dispatched loops took 3% off the area-to-area stage even with timing off.
    pub fn time_queries(&self, on: bool) {
        self.query_nanos.store(0, Ordering::Relaxed);
        self.timing.store(on, Ordering::Relaxed);
    }

    /// Seconds spent inside the estimators' query batches since
    /// [`Visibility::time_queries`] turned timing on, summed over the threads that made
    /// them.
    pub fn query_seconds(&self) -> f64 {
        self.query_nanos.load(Ordering::Relaxed) as f64 * 1e-9
    }

    /// Runs the query batch `f`, adding its time to the total.
    #[inline(never)]
    fn timed<R>(&self, f: impl FnOnce() -> R) -> R {
        let t = Instant::now();
        let r = f();
        self.query_nanos
            .fetch_add(t.elapsed().as_nanos() as u64, Ordering::Relaxed);
        r
    }

    /// The offset used for ray ends (closest-hit origins, and segment ends far enough
    /// from the other end's plane).
    pub fn eps(&self) -> f32 {
        self.offsets.eps
    }

    /// The ray-offset policy ([`Offsets`]).
    pub fn offsets(&self) -> Offsets {
        self.offsets
    }

    /// The underlying Embree scene, for the benchmark's raw query loops only: Embree
    /// types do not leave the crate.
    pub(crate) fn raw(&self) -> &EmbreeScene {
        &self.scene
    }

    /// How 16-ray packets are traced ([`PacketWidth`]).
    pub fn packet_width(&self) -> PacketWidth {
        self.scene.packet_width()
    }

    /// Traces 16-ray packets as `w` from now on, whatever the library runs natively (the
    /// bench's `--packets`; the answers are the same).
    pub fn set_packet_width(&mut self, w: PacketWidth) {
        self.scene.set_packet_width(w);
    }

    /// The Embree version, as `major.minor.patch`.
    pub fn embree_version(&self) -> String {
        self.scene.version()
    }

    /// The segment from `x` (on a surface with unit normal `n_x`) to `y` (normal `n_y`),
    /// both ends offset off their surfaces toward the other end by the [`Offsets`]
    /// policy, as an `f32` ray: `(origin, direction, tfar)` with tnear = [`SEGMENT_TNEAR`]. Computed in
    /// f64, rounded once. Direction is not normalised.
    #[inline]
    pub fn segment_ray(&self, x: DVec3, n_x: DVec3, y: DVec3, n_y: DVec3) -> SegmentRay {
        let d = y - x;
        let (cx, cy) = (n_x.dot(d), n_y.dot(d));
        let ox = if cx >= 0.0 { n_x } else { -n_x };
        let oy = if cy <= 0.0 { n_y } else { -n_y };
        let (dx, dy) = self.offsets.ends(cx.abs() as f32, cy.abs() as f32);
        // Each end kept `floor` in front of the other end's plane too (module docs).
        let floor = f64::from(self.offsets.floor);
        let org = x + ox * f64::from(dx) + oy * (floor - cy.abs()).max(0.0);
        let end = y + oy * f64::from(dy) + ox * (floor - cx.abs()).max(0.0);
        (org.as_vec3(), (end - org).as_vec3(), SEGMENT_TFAR)
    }

    /// Visibility of up to 16 segments at once, with Embree's packet query.
    #[inline]
    pub fn segments_visible16(&self, segs: &[SegmentRay], out: &mut [bool]) {
        self.scene.occluded16_segments(segs, SEGMENT_TNEAR, out);
        for v in out[..segs.len()].iter_mut() {
            *v = !*v;
        }
    }

    /// Visibility of a batch of segment rays (as made by [`Visibility::segment_ray`]):
    /// `out[k]` is true when segment k is free. Whole chunks of 16 go through Embree's
    /// packets ([`PacketWidth`]), the rest one `rtcOccluded1` each (or, in 8-wide halves,
    /// as each half decides): the rays of one pair of patches are coherent, and on the
    /// 400-patch Cornell box packets of them ran 1.7 to 2.2 times the single-ray rate
    /// (`docs/PERFORMANCE.md`, section 2).
    #[inline]
    pub fn segments_visible(&self, segs: &[SegmentRay], out: &mut [bool]) {
        let min = self.short_packet_min(16);
        for (c, o) in segs.chunks(16).zip(out.chunks_mut(16)) {
            if c.len() >= min {
                self.segments_visible16(c, o);
            } else {
                for (o, s) in o.iter_mut().zip(c) {
                    *o = !self.scene.occluded1(s.0, s.1, SEGMENT_TNEAR, s.2);
                }
            }
        }
    }

    /// Fewest rays of a run shorter than 16 that go to Embree as a packet: `wide` where
    /// 16-wide packets are native; every run where they go as two 8-wide halves, each
    /// half deciding for itself ([`embree::HALF_MIN`]).
    #[inline]
    fn short_packet_min(&self, wide: usize) -> usize {
        match self.scene.packet_width() {
            PacketWidth::Sixteen => wide,
            PacketWidth::Eight => 1,
        }
    }

    /// [`Visibility::segments_visible`] of segment rays given as structure of arrays: one
    /// packet per 16 rays ([`PacketWidth`]), each filled by copying 16-float runs; where
    /// packets are 16-wide, a last run of fewer than [`PACKET_MIN`] rays goes one
    /// `rtcOccluded1` per ray.
    #[inline]
    pub fn segments_visible_soa(&self, segs: &Segments, out: &mut [bool]) {
        let n = segs.len();
        let mut packet = SegmentPacket16::new();
        // The packet copies and the answers' pass, at the sampling passes' width.
        crate::simd::with_widest(
            #[inline(always)]
            || {
                for ((org, dir), out) in segs.rays.packets16().zip(out[..n].chunks_mut(16)) {
                    let len = org[0].len();
                    if len >= self.short_packet_min(PACKET_MIN) {
                        self.scene
                            .free16_soa(&mut packet, org, dir, SEGMENT_TNEAR, segs.tfar, out);
                    } else {
                        for (k, v) in out.iter_mut().enumerate().take(len) {
                            let o = Vec3::new(org[0][k], org[1][k], org[2][k]);
                            let d = Vec3::new(dir[0][k], dir[1][k], dir[2][k]);
                            *v = !self.scene.occluded1(o, d, SEGMENT_TNEAR, segs.tfar);
                        }
                    }
                }
            },
        )
    }

    /// The ray [`Visibility::first_hit`] casts from `x` (normal `n_x`) in unit direction
    /// `dir`: its origin, offset off the surface toward `dir` by `eps`, rounded to f32.
    #[inline]
    pub fn first_hit_origin(&self, x: DVec3, n_x: DVec3, dir: DVec3) -> Vec3 {
        let off = if n_x.dot(dir) >= 0.0 { n_x } else { -n_x };
        (x + off * f64::from(self.offsets.eps)).as_vec3()
    }

    /// The patch whose front side each ray meets first, for rays given as structure of
    /// arrays: `out[k]` is that patch, or [`NO_HIT`] when ray k hits nothing or first
    /// meets the back of a patch (which receives nothing: the ray is absorbed there). 16
    /// rays at a time through `rtcIntersect16` (the last packet partly filled); the side
    /// comes from the hit triangle's geometric normal, oriented once per triangle against
    /// its patch's normal. Packets pay when the rays of one are coherent: hemisphere rays
    /// from one patch, in Z-order of their direction cells, ran 1.2 to 1.3 times the
    /// single-ray rate (`docs/PERFORMANCE.md`).
    #[inline]
    pub fn first_front_hits_soa(&self, rays: &Rays, out: &mut [u32]) {
        let n = rays.len();
        let mut against = [false; 16];
        let mut packet = HitPacket16::new();
        // The packet copies and the answers' pass, at the sampling passes' width.
        crate::simd::with_widest(
            #[inline(always)]
            || {
                for ((org, dir), out) in rays.packets16().zip(out[..n].chunks_mut(16)) {
                    self.scene.intersect16_soa(
                        &mut packet,
                        org,
                        dir,
                        self.offsets.floor,
                        out,
                        &mut against,
                    );
                    for (k, (v, &a)) in out.iter_mut().zip(&against).enumerate() {
                        if *v != u32::MAX {
                            let (u, w) = packet.uv(k);
                            let (front, back, along) = self.sides(*v, u, w);
                            *v = if a == along { front } else { back };
                        }
                    }
                }
            },
        )
    }

    /// First patch hit by the ray leaving `x` (normal `n_x`) in unit direction `dir`: of
    /// the two sides of a two-sided face, the one facing the ray.
    #[inline]
    pub fn first_hit(&self, x: DVec3, n_x: DVec3, dir: DVec3) -> Option<Hit> {
        let org = self.first_hit_origin(x, n_x, dir);
        self.scene
            .intersect1(org, dir.as_vec3(), self.offsets.floor, f32::INFINITY)
            .map(|h| {
                let (front, back, along) = self.sides(h.prim, h.u, h.v);
                // Meeting the back of a two-sided face is meeting the front of its twin.
                let patch = if h.against == along || back == NO_HIT {
                    front
                } else {
                    back
                };
                Hit { patch, t: h.t }
            })
    }
}

/// A planar face traced as its own one or two triangles instead of its patches' (a quad
/// `p0..p3` as `(p0, p1, p2)` and `(p0, p2, p3)`, the way its patches are split). A hit
/// names its patch by where it falls on the face: from the hit's barycentric coordinates,
/// the face's grid cell ([`Cut::cell`]). The patches' triangles tile the face exactly (the
/// cells of a planar bilinear grid have straight sides), which is why this is the same
/// scene (module docs).
#[derive(Clone, Copy, Debug)]
struct Whole {
    /// The face's first patch.
    first: u32,
    /// The first patch of its back (the twins of its patches, in the same order), or
    /// [`NO_HIT`] for a one-sided face.
    back: u32,
    /// Its grid.
    cut: Cut,
}

/// The grid of a face traced whole ([`crate::mesh::Layout`]).
#[derive(Clone, Copy, Debug)]
enum Cut {
    /// A triangle cut into `n²` similar triangles.
    Triangle { n: u32 },
    /// A parallelogram cut into `nu x nv` parallelograms.
    Parallelogram { nu: u32, nv: u32 },
    /// Any other planar convex quad, cut along its bilinear map's lines; `q` holds
    /// `p1 - p0`, `p2 - p0`, `p3 - p0` in coordinates of the face's plane.
    Quad { nu: u32, nv: u32, q: [DVec2; 3] },
}

impl Cut {
    /// The patch, counted from the face's first, of the point with barycentrics `(u, v)`
    /// in half `h` of the face (its triangle `(p0, p1, p2)` or `(p0, p2, p3)`). Points just
    /// outside the face (rounding) go to the nearest cell.
    #[inline(always)]
    fn cell(&self, h: u32, u: f64, v: f64) -> u32 {
        match *self {
            Cut::Triangle { n } => {
                let (x, y) = (u * f64::from(n), v * f64::from(n));
                let r = (y.max(0.0) as u32).min(n - 1);
                let a = (x.max(0.0) as u32).min(n - 1 - r);
                let down = x - f64::from(a) + y - f64::from(r) > 1.0 && a + 1 < n - r;
                r * (2 * n - r) + 2 * a + u32::from(down)
            }
            Cut::Parallelogram { nu, nv } => {
                let (s, t) = if h == 0 { (u + v, v) } else { (u, u + v) };
                grid_cell(s, t, nu, nv)
            }
            Cut::Quad { nu, nv, q } => {
                let x = if h == 0 {
                    q[0] * u + q[1] * v
                } else {
                    q[1] * u + q[2] * v
                };
                let (s, t) = inverse_bilinear(q[0], q[2], q[1] - q[0] - q[2], x);
                grid_cell(s, t, nu, nv)
            }
        }
    }
}

/// Patch `b nu + a` of the cell of `(s, t)` in a `nu x nv` grid of the unit square,
/// clamped into it.
#[inline(always)]
fn grid_cell(s: f64, t: f64, nu: u32, nv: u32) -> u32 {
    let a = ((s * f64::from(nu)).max(0.0) as u32).min(nu - 1);
    let b = ((t * f64::from(nv)).max(0.0) as u32).min(nv - 1);
    b * nu + a
}

/// What [`Visibility::new`] hands Embree, and how to read its hits.
struct Traced {
    triangles: Vec<[u32; 3]>,
    front: Vec<u32>,
    back: Vec<u32>,
    wholes: Vec<Whole>,
}

impl Traced {
    /// The faces of `patches.grids` that can be traced whole, whole; every other face's
    /// patch triangles as they are. A quad goes whole when its fourth corner lies within
    /// `1e-3` of the ray offset `eps` of the plane of the other three (closer than the
    /// `f32` rounding of the scene's coordinates, so that it changes no answer beyond
    /// rounding); its back (of a two-sided face) goes with it.
    fn of(patches: &PatchSet, offsets: Offsets) -> Traced {
        let v = &patches.vertices;
        let mut t = Traced {
            triangles: Vec::new(),
            front: Vec::new(),
            back: Vec::new(),
            wholes: Vec::new(),
        };
        // The back of a two-sided face lies on its front unless one side was raised off a
        // face it lay on (`Scene::raise_coincident`); then each side is traced on its own.
        // (Patch `p` and its twin, when it has one, share corner 0's position.)
        let lies_on = |p: u32| {
            let p = p as usize;
            patches.twin_of(p).is_some_and(|t| {
                v[patches.corners[p][0] as usize] == v[patches.corners[t][0] as usize]
            })
        };
        let mut whole_of = vec![NO_HIT; patches.grids.len()];
        let fits = patches.grids.len() < (WHOLE / 2) as usize;
        for (fi, g) in patches.grids.iter().enumerate() {
            let cut = match g.layout {
                _ if !fits => None,
                Layout::Triangle { n } => Some(Cut::Triangle { n }),
                Layout::Quad { nu, nv } => {
                    let p = g.corners.map(|k| v[k as usize]);
                    quad_cut(p, nu, nv, f64::from(offsets.eps) * 1e-3)
                }
                Layout::Back { .. } => None,
            };
            if let Some(cut) = cut {
                whole_of[fi] = t.wholes.len() as u32;
                t.wholes.push(Whole {
                    first: g.first,
                    back: NO_HIT,
                    cut,
                });
            }
        }
        let normal = &patches.normal;
        let add = |t: &mut Traced, tri: [u32; 3], front: u32, n: DVec3, back: u32| {
            let [a, b, c] = tri.map(|k| v[k as usize]);
            let along = (b - a).cross(c - a).dot(n) > 0.0;
            t.triangles.push(tri);
            t.front.push(front | if along { ALONG } else { 0 });
            t.back.push(back);
        };
        for (fi, g) in patches.grids.iter().enumerate() {
            let w = whole_of[fi];
            if w != NO_HIT {
                let c = g.corners;
                let n = normal[g.first as usize];
                add(&mut t, [c[0], c[1], c[2]], WHOLE | (2 * w), n, NO_HIT);
                if c[3] != NONE {
                    add(&mut t, [c[0], c[2], c[3]], WHOLE | (2 * w + 1), n, NO_HIT);
                }
            } else if let Layout::Back { front } = g.layout {
                let wf = whole_of[front as usize];
                if wf != NO_HIT && lies_on(g.first) {
                    // Front and back of a two-sided face lie on each other: the front's
                    // triangles serve both, a ray meeting their back side having met the
                    // back face's front.
                    t.wholes[wf as usize].back = g.first;
                }
            }
        }
        // Every patch not on a face traced whole (all of them when there are no grids).
        for (tri, &p) in patches.triangles.iter().zip(&patches.tri_patch) {
            let face = patches.face[p as usize] as usize;
            let on_whole = match patches.grids.get(face).map(|g| g.layout) {
                Some(Layout::Back { front }) => {
                    whole_of[front as usize] != NO_HIT && lies_on(patches.grids[face].first)
                }
                Some(_) => whole_of[face] != NO_HIT,
                None => false,
            };
            if !on_whole {
                // Both sides of a two-sided face are traced, lying on each other: a ray
                // meets both at one distance and Embree reports either; from the back of
                // one it has met the front of the other (not so when they lie apart).
                let twin = patches
                    .twin_of(p as usize)
                    .filter(|_| lies_on(p))
                    .map_or(NO_HIT, |t| t as u32);
                add(&mut t, *tri, p, normal[p as usize], twin);
            }
        }
        t
    }
}

/// The [`Cut`] of a quad face with corners `p`, if it is planar within `tol`.
fn quad_cut(p: [DVec3; 4], nu: u32, nv: u32, tol: f64) -> Option<Cut> {
    let n = (p[1] - p[0]).cross(p[2] - p[0]).normalize_or_zero();
    if n == DVec3::ZERO || n.dot(p[3] - p[0]).abs() > tol {
        return None;
    }
    let skew = p[0] + p[2] - p[1] - p[3];
    if skew.length_squared() <= 1e-24 * (p[2] - p[0]).length_squared() {
        return Some(Cut::Parallelogram { nu, nv });
    }
    let x = (p[1] - p[0]).normalize();
    let y = n.cross(x);
    let at = |q: DVec3| DVec2::new((q - p[0]).dot(x), (q - p[0]).dot(y));
    Some(Cut::Quad {
        nu,
        nv,
        q: [at(p[1]), at(p[2]), at(p[3])],
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::Resolution;
    use crate::scene::{obj, Scene};
    use std::path::Path;

    /// A scene of faces apart from each other: a square, a skewed parallelogram, a
    /// trapezoid, a triangle (traced whole) and a quad 0.2% off planar (by its patches).
    fn faces(two_sided: bool) -> Scene {
        let text = "\
v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n\
v 3 0 0\nv 3 1 0.3\nv 3 1.4 1.3\nv 3 0.4 1\n\
v 0 3 0\nv 0.5 3 1\nv 1.5 3 1\nv 2 3 0\n\
v -3 0 0\nv -2 0.5 0.2\nv -2.6 1.1 0.9\n\
v 0 -3 0\nv 1 -3 0\nv 1 -3 1\nv 0 -3.002 1\n\
f 1 2 3 4\nf 5 6 7 8\nf 9 10 11 12\nf 13 14 15\nf 16 17 18 19\n";
        let mut s = obj::parse("faces", Path::new("faces.obj"), text, &|_| unreachable!()).unwrap();
        s.make_two_sided(two_sided);
        s
    }

    /// A two-sided box on a two-sided floor: the inside of the box's bottom, raised off the
    /// floor it lay on (`Scene::raise_coincident`), is traced on its own, not as the back
    /// of its outside (still on the floor): a segment from the box's lid down to
    /// the floor under the box is blocked, and a first-hit ray from the lid meets the
    /// bottom's inside.
    #[test]
    fn a_raised_inside_of_a_two_sided_face_is_traced_where_it_lies() {
        let text = "o floor\nv -2 0 -2\nv -2 0 2\nv 2 0 2\nv 2 0 -2\nf 1 2 3 4\n\
             o box\nv 0 0 0\nv 1 0 0\nv 1 0 1\nv 0 0 1\nv 0 1 0\nv 1 1 0\nv 1 1 1\nv 0 1 1\n\
             f 5 6 7 8\nf 9 12 11 10\nf 5 9 10 6\nf 6 10 11 7\nf 7 11 12 8\nf 8 12 9 5\n";
        let mut s = obj::parse("box", Path::new("box.obj"), text, &|_| unreachable!()).unwrap();
        s.make_two_sided(true);
        assert_eq!(s.raise_coincident().len(), 1);
        let patches = PatchSet::build(&s, Resolution::Patches(1)).unwrap();
        let vis = Visibility::new(&patches).unwrap();
        let (lid, floor) = (DVec3::new(0.5, 1.0, 0.5), DVec3::new(0.3, 0.0, 0.6));
        let seg = vis.segment_ray(lid, DVec3::NEG_Y, floor, DVec3::Y);
        let mut free = [true];
        vis.segments_visible(&[seg], &mut free);
        assert!(!free[0], "the floor under the box is seen from inside it");
        let hit = vis
            .first_hit(lid, DVec3::NEG_Y, DVec3::NEG_Y)
            .expect("a hit");
        let inside = s.faces[1].twin;
        assert_eq!(patches.face[hit.patch as usize], inside, "{hit:?}");
        assert!(patches.centroid[hit.patch as usize].y > 0.0);
    }

    /// Inside the closed unit cube every segment between two of its faces is free, even
    /// from a point within `f32` rounding of the edge the two faces share (which, rounded
    /// onto the other face's plane, would run inside that face without the `floor` margin
    /// off it).
    #[test]
    fn segments_from_a_shared_edge_stay_off_the_other_face() {
        let patches =
            PatchSet::build(&Scene::load("cube").unwrap(), Resolution::Patches(6)).unwrap();
        let vis = Visibility::new(&patches).unwrap();
        // The wall x = 1 (normal -x) and the ceiling y = 1 (normal -y) meet along x = y = 1.
        let (n_wall, n_ceiling) = (DVec3::NEG_X, DVec3::NEG_Y);
        let mut segs = Vec::new();
        for delta in [0.0, 1e-12, 1e-9, 1e-8, 3e-8, 1e-7, 1e-6] {
            for z in [0.1, 0.5, 0.9] {
                let x = DVec3::new(1.0, 1.0 - delta, z);
                for y in [
                    DVec3::new(0.5, 1.0, 0.9),
                    DVec3::new(0.999, 1.0, z),
                    DVec3::new(0.01, 1.0, 0.2),
                ] {
                    segs.push(vis.segment_ray(x, n_wall, y, n_ceiling));
                    segs.push(vis.segment_ray(y, n_ceiling, x, n_wall));
                }
            }
        }
        let mut free = vec![false; segs.len()];
        vis.segments_visible(&segs, &mut free);
        let blocked: Vec<_> = segs.iter().zip(&free).filter(|(_, &f)| !f).collect();
        assert!(blocked.is_empty(), "blocked: {blocked:?}");
    }

    /// Inside the closed unit cube a segment from a point within `f32` rounding of a
    /// concave edge to a point on a third face is free: the end, offset off its own face
    /// and rounded to `f32`, may lie on the face across the edge, which a ray from there
    /// must not count as hit at its start.
    #[test]
    fn segments_from_a_concave_edge_leave_the_face_across_it() {
        let patches =
            PatchSet::build(&Scene::load("cube").unwrap(), Resolution::Patches(6)).unwrap();
        let vis = Visibility::new(&patches).unwrap();
        // The wall x = 1 (normal -x) meets the ceiling y = 1 along x = y = 1; the far ends
        // lie on the floor y = 0 (normal +y) and the wall x = 0 (normal +x).
        let mut segs = Vec::new();
        for delta in [0.0, 1e-12, 1e-9, 1e-8, 2e-8, 3e-8, 5e-8] {
            for z in [0.1, 0.19, 0.5, 0.9] {
                let x = DVec3::new(1.0, 1.0 - delta, z);
                for (y, n_y) in [
                    (DVec3::new(0.5, 0.0, 0.9), DVec3::Y),
                    (DVec3::new(0.3, 0.0, z), DVec3::Y),
                    (DVec3::new(0.0, 0.9, 0.2), DVec3::X),
                    (DVec3::new(0.0, 0.2, 0.7), DVec3::X),
                ] {
                    segs.push(vis.segment_ray(x, DVec3::NEG_X, y, n_y));
                    segs.push(vis.segment_ray(y, n_y, x, DVec3::NEG_X));
                }
            }
        }
        let mut free = vec![false; segs.len()];
        vis.segments_visible(&segs, &mut free);
        let mut one = vec![false; segs.len()];
        for (k, s) in segs.iter().enumerate() {
            vis.segments_visible(std::slice::from_ref(s), &mut one[k..k + 1]);
        }
        let blocked: Vec<_> = segs.iter().zip(&free).filter(|(_, &f)| !f).collect();
        assert!(blocked.is_empty(), "blocked in packets: {blocked:?}");
        assert!(one.iter().all(|&f| f), "blocked one at a time");
    }

    /// Closest-hit rays from a point within `f32` rounding of the cube's concave edge,
    /// into the room, meet the face they are aimed at, not the face across the edge
    /// (from its back, as nothing) at their start: one ray at a time and in packets.
    #[test]
    fn closest_hits_from_a_concave_edge_leave_the_face_across_it() {
        let patches =
            PatchSet::build(&Scene::load("cube").unwrap(), Resolution::Patches(6)).unwrap();
        let vis = Visibility::new(&patches).unwrap();
        let floor = (0..patches.len())
            .find(|&p| patches.centroid[p].y < 1e-9)
            .unwrap() as u32;
        let (mut org, mut dir) = (Vec::new(), Vec::new());
        for delta in [0.0, 1e-12, 1e-9, 1e-8, 3e-8, 5e-8] {
            for z in [0.1, 0.19, 0.5, 0.9] {
                let x = DVec3::new(1.0, 1.0 - delta, z);
                for aim in [DVec3::new(0.5, 0.0, 0.9), DVec3::new(0.3, 0.0, z)] {
                    let d = (aim - x).normalize();
                    let hit = vis.first_hit(x, DVec3::NEG_X, d).map(|h| h.patch);
                    assert_eq!(hit, Some(floor), "from {x} toward {aim}");
                    org.push(vis.first_hit_origin(x, DVec3::NEG_X, d));
                    dir.push(d.as_vec3());
                }
            }
        }
        let col = |a: &[Vec3], c: usize| a.iter().map(|p| p[c]).collect::<Vec<f32>>();
        let (o, d) = (
            [col(&org, 0), col(&org, 1), col(&org, 2)],
            [col(&dir, 0), col(&dir, 1), col(&dir, 2)],
        );
        let rays = Rays {
            org: [&o[0], &o[1], &o[2]],
            dir: [&d[0], &d[1], &d[2]],
        };
        let mut out = vec![0; org.len()];
        vis.first_front_hits_soa(&rays, &mut out);
        assert!(out.iter().all(|&p| p == floor), "{out:?}");
    }

    /// Every patch of both scenes, hit at 16 inner points from the front, obliquely, and
    /// from the back, is named alike by the faces traced whole and by the patch
    /// triangles, and is the patch aimed at (or its twin, or nothing, from the back).
    #[test]
    fn whole_faces_name_the_patch_hit() {
        for two_sided in [false, true] {
            let patches = PatchSet::build(&faces(two_sided), Resolution::MaxEdge(0.13)).unwrap();
            let whole = Visibility::new(&patches).unwrap();
            let flat = Visibility::new(&PatchSet {
                grids: Vec::new(),
                ..patches.clone()
            })
            .unwrap();
            assert_eq!(
                whole.whole_faces(),
                4,
                "the off-planar quad goes by its patches"
            );
            assert!(whole.traced_triangles() < flat.traced_triangles() / 4);
            let mut checked = 0;
            for p in 0..patches.len() {
                let n = patches.normal[p];
                let side = n.any_orthonormal_vector();
                let s = patches.sampler(p);
                let twin = patches.twin_of(p).map_or(NO_HIT, |t| t as u32);
                for (a, b) in (0..16).map(|k| {
                    (
                        0.1 + 0.8 * (k % 4) as f64 / 3.0,
                        0.1 + 0.8 * (k / 4) as f64 / 3.0,
                    )
                }) {
                    let x = s.point(a, b);
                    for (dir, want) in [
                        (-n, p as u32),
                        ((side - n).normalize(), p as u32),
                        (n, twin),
                    ] {
                        let o = (x - dir * 0.05).as_vec3();
                        let d = dir.as_vec3();
                        let rays = Rays {
                            org: [&[o.x], &[o.y], &[o.z]],
                            dir: [&[d.x], &[d.y], &[d.z]],
                        };
                        let (mut w, mut f) = ([0u32], [0u32]);
                        whole.first_front_hits_soa(&rays, &mut w);
                        flat.first_front_hits_soa(&rays, &mut f);
                        assert_eq!(
                            (w[0], f[0]),
                            (want, want),
                            "patch {p}, {dir:?}, two-sided {two_sided}"
                        );
                        let one = |v: &Visibility| {
                            v.scene.intersect1(o, d, 0.0, f32::INFINITY).map(|h| {
                                let (front, back, along) = v.sides(h.prim, h.u, h.v);
                                if h.against == along {
                                    front
                                } else {
                                    back
                                }
                            })
                        };
                        assert_eq!(one(&whole), Some(want), "patch {p}, {dir:?}");
                        let hit = whole.first_hit(x - dir * 0.05, n, dir).map(|h| h.patch);
                        let want_hit = if want == NO_HIT { p as u32 } else { want };
                        assert_eq!(hit, Some(want_hit), "patch {p}, {dir:?}");
                        checked += 1;
                    }
                }
            }
            assert!(checked > 3000, "{checked}");
        }
    }
}
