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
//! `tnear`/`tfar`). Because both ends sit on the front side of their patches, a segment
//! never hits its own patches, and a point in a corner cannot leak through the wall it
//! touches. Both bounds scale with the scene, so a scaled copy casts the same rays, scaled.
//! Closest-hit rays leave from `eps` off their surface.

mod embree;

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Instant;

use glam::{DVec3, Vec3};

use crate::error::Result;
use crate::mesh::PatchSet;

pub use embree::flush_denormals;
pub use embree::PacketWidth;
pub(crate) use embree::{EmbreeScene, HitPacket16, SegmentPacket16};

/// Relative offset of ray ends from their surfaces, as a fraction of the scene diagonal.
pub const OFFSET_REL: f32 = 1e-5;

/// `tfar` of a segment ray: it stops this fraction of its length short of the far end.
pub const SEGMENT_TFAR: f32 = 1.0 - 1e-4;

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

/// A segment ray `(origin, direction, tfar)` with tnear = 0, as made by
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
/// `t` in `[0, tfar]`. This is the layout of Embree's packets, so a batch goes to
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

/// Visibility queries over the patch triangles of a [`PatchSet`].
pub struct Visibility {
    scene: EmbreeScene,
    tri_patch: Vec<u32>,
    /// Patch of each triangle, with bit 31 set when the triangle's winding normal points
    /// to the patch's front side ([`Visibility::first_front_hits_soa`]).
    tri_front: Vec<u32>,
    /// For each triangle, the patch a ray meeting its back reaches: the twin of its patch
    /// (the other side of a two-sided face, lying on it) or [`NO_HIT`].
    tri_back: Vec<u32>,
    /// Patch normals, kept only when some patch has a twin (for [`Visibility::first_hit`]).
    twin_normal: Vec<DVec3>,
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

impl Visibility {
    /// Builds the acceleration structure over the patches' triangles.
    pub fn new(patches: &PatchSet) -> Result<Visibility> {
        let v32: Vec<Vec3> = patches.vertices.iter().map(|v| v.as_vec3()).collect();
        let scene = EmbreeScene::new(&v32, &patches.triangles)?;
        let v = &patches.vertices;
        let tri_front = patches
            .triangles
            .iter()
            .zip(&patches.tri_patch)
            .map(|(t, &p)| {
                let [a, b, c] = t.map(|k| v[k as usize]);
                let along = (b - a).cross(c - a).dot(patches.normal[p as usize]) > 0.0;
                p | if along { ALONG } else { 0 }
            })
            .collect();
        // Front and back of a two-sided face lie on each other: a ray meets both at one
        // distance, and Embree reports either; from the back of one it has met the front
        // of the other.
        let tri_back = patches
            .tri_patch
            .iter()
            .map(|&p| patches.twin_of(p as usize).map_or(NO_HIT, |t| t as u32))
            .collect();
        Ok(Visibility {
            scene,
            tri_patch: patches.tri_patch.clone(),
            tri_front,
            tri_back,
            twin_normal: if patches.twin.is_empty() {
                Vec::new()
            } else {
                patches.normal.clone()
            },
            offsets: Offsets::of(patches),
            timing: AtomicBool::new(false),
            query_nanos: AtomicU64::new(0),
        })
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
    /// policy, as an `f32` ray: `(origin, direction, tfar)` with tnear = 0. Computed in
    /// f64, rounded once. Direction is not normalised.
    #[inline]
    pub fn segment_ray(&self, x: DVec3, n_x: DVec3, y: DVec3, n_y: DVec3) -> SegmentRay {
        let d = y - x;
        let (cx, cy) = (n_x.dot(d), n_y.dot(d));
        let ox = if cx >= 0.0 { n_x } else { -n_x };
        let oy = if cy <= 0.0 { n_y } else { -n_y };
        let (dx, dy) = self.offsets.ends(cx.abs() as f32, cy.abs() as f32);
        let org = x + ox * f64::from(dx);
        let end = y + oy * f64::from(dy);
        (org.as_vec3(), (end - org).as_vec3(), SEGMENT_TFAR)
    }

    /// Visibility of up to 16 segments at once, with Embree's packet query.
    #[inline]
    pub fn segments_visible16(&self, segs: &[SegmentRay], out: &mut [bool]) {
        self.scene.occluded16_segments(segs, out);
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
                    *o = !self.scene.occluded1(s.0, s.1, 0.0, s.2);
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
                        self.scene.free16_soa(&mut packet, org, dir, segs.tfar, out);
                    } else {
                        for (k, v) in out.iter_mut().enumerate().take(len) {
                            let o = Vec3::new(org[0][k], org[1][k], org[2][k]);
                            let d = Vec3::new(dir[0][k], dir[1][k], dir[2][k]);
                            *v = !self.scene.occluded1(o, d, 0.0, segs.tfar);
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
                    self.scene
                        .intersect16_soa(&mut packet, org, dir, out, &mut against);
                    for (v, &a) in out.iter_mut().zip(&against) {
                        if *v != u32::MAX {
                            let t = self.tri_front[*v as usize];
                            *v = if a == (t & ALONG != 0) {
                                t & !ALONG
                            } else {
                                self.tri_back[*v as usize]
                            };
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
            .intersect1(org, dir.as_vec3(), 0.0, f32::INFINITY)
            .map(|h| {
                let k = h.prim as usize;
                let mut patch = self.tri_patch[k];
                let twin = self.tri_back[k];
                if twin != NO_HIT && self.twin_normal[patch as usize].dot(dir) > 0.0 {
                    // The ray meets the back of `patch`: the front of its twin.
                    patch = twin;
                }
                Hit { patch, t: h.t }
            })
    }
}
