//! The only `unsafe` code in the crate: a small safe layer over `embree4-sys`.
//!
//! `embree4-rs` 0.0.16 has no occlusion query and keeps its scene handle private, so this
//! module talks to the C API directly: a device, one committed triangle scene, occlusion
//! (`rtcOccluded1`, `rtcOccluded16` or two `rtcOccluded8`) and closest-hit (`rtcIntersect1`,
//! `rtcIntersect16` or two `rtcIntersect8`) queries, 16-ray packets at the width the
//! library runs natively ([`PacketWidth`]), and Embree errors turned into [`Error::Embree`].
//!
//! Embree rules this module relies on (Embree 4 API reference):
//! - a committed scene may be queried from any number of threads at once (`rtcCommitScene`);
//! - queries do no error checking: errors surface through the device error callback and
//!   `rtcGetDeviceError`, which are checked after every build step and after commit;
//! - buffers created with `rtcSetNewGeometryBuffer` are owned by Embree, 16-byte padded.
#![allow(unsafe_code)]

use std::ffi::{c_char, c_void, CStr};
use std::ptr::null_mut;
use std::sync::Mutex;

use embree4_sys as sys;
use glam::Vec3;

use crate::error::Error;

/// Where the error callback leaves the message of the last Embree error.
struct ErrorSink {
    last: Mutex<Option<String>>,
}

unsafe extern "C" fn error_callback(user: *mut c_void, code: sys::RTCError, msg: *const c_char) {
    // SAFETY: `user` is the `ErrorSink` boxed in `EmbreeScene`, alive as long as the device;
    // `msg` is a NUL-terminated string owned by Embree for the duration of the call.
    let sink = unsafe { &*(user as *const ErrorSink) };
    let text = if msg.is_null() {
        String::new()
    } else {
        unsafe { CStr::from_ptr(msg) }
            .to_string_lossy()
            .into_owned()
    };
    if let Ok(mut last) = sink.last.lock() {
        *last = Some(format!("{code:?}: {text}"));
    }
}

/// A committed Embree scene of one triangle mesh, ready for queries from many threads.
pub struct EmbreeScene {
    device: sys::RTCDevice,
    scene: sys::RTCScene,
    sink: Box<ErrorSink>,
    /// Whether 16-ray packets go to Embree as one `rtcOccluded16`/`rtcIntersect16`
    /// (where the library reports 16-wide packets as native, AVX-512) or as two 8-wide
    /// queries ([`PacketWidth`]).
    wide16: bool,
}

/// How a 16-ray packet is handed to Embree.
///
/// Embree traces 16-wide packets natively only with AVX-512; elsewhere (AVX2) it takes
/// `rtcOccluded16` apart ray by ray, and the packet ran *slower* than single rays, while
/// two native 8-wide queries ran 1.5 times faster than it (400-patch Cornell box,
/// `radiosity bench --packets 16` and `--packets 8` on an AVX2 processor:
/// docs/PERFORMANCE.md, section 1). So the width follows what the library reports as
/// native (`RTC_DEVICE_PROPERTY_NATIVE_RAY16_SUPPORTED`) unless the bench asks otherwise.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PacketWidth {
    /// One `rtcOccluded16` / `rtcIntersect16`.
    Sixteen,
    /// Two `rtcOccluded8` / `rtcIntersect8` over its halves.
    Eight,
}

impl std::fmt::Display for PacketWidth {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            PacketWidth::Sixteen => "16-wide",
            PacketWidth::Eight => "2 x 8-wide",
        })
    }
}

/// Fewest rays of a half packet traced as one `rtcOccluded8`; fewer go one
/// `rtcOccluded1` each. On `room-spheres-12-s4` (hierarchical, clusters), whose links
/// trace runs of 4 to 16 rays, 6 took 3-4% less CPU than 8, 4 and 1 took 3% and 6% more
/// (whole-process A/B pairs; the same bits).
pub const HALF_MIN: usize = 6;

/// The valid mask of an 8-wide packet query, aligned like the packet.
#[repr(C, align(32))]
struct Valid8([i32; 8]);

impl Valid8 {
    /// The first `m` lanes valid.
    #[inline(always)]
    fn first(m: usize) -> Valid8 {
        let mut v = Valid8([0i32; 8]);
        v.0[..m].fill(-1);
        v
    }
}

/// Lanes `[lo, lo + 8)` of a 16-wide packet as an 8-wide one: origins, directions, `tnear`
/// and `tfar` copied, the fields no query reads set as a fresh packet has them.
#[inline(always)]
fn half_of(p: &sys::RTCRay16, lo: usize) -> sys::RTCRay8 {
    let lanes = |a: &[f32; 16]| -> [f32; 8] { a[lo..lo + 8].try_into().unwrap() };
    sys::RTCRay8 {
        org_x: lanes(&p.org_x),
        org_y: lanes(&p.org_y),
        org_z: lanes(&p.org_z),
        tnear: lanes(&p.tnear),
        dir_x: lanes(&p.dir_x),
        dir_y: lanes(&p.dir_y),
        dir_z: lanes(&p.dir_z),
        time: [0.0; 8],
        tfar: lanes(&p.tfar),
        mask: [u32::MAX; 8],
        id: [0; 8],
        flags: [0; 8],
    }
}

/// `RTCRayHit8` with spare room after it (8 lanes of `instPrimID`), as [`PaddedRayHit`].
#[repr(C, align(32))]
struct PaddedRayHit8 {
    rayhit: sys::RTCRayHit8,
    _spare: [u32; 16],
}

/// Traces lanes `[8h, 8h + 8)` of a 16-wide occlusion packet, `n` valid lanes in all, as
/// one `rtcOccluded8` (or ray by ray when fewer than [`HALF_MIN`] of them are valid), and
/// writes back their `tfar` (what an occlusion query changes).
#[inline(always)]
fn occluded_half(scene: sys::RTCScene, p: &mut sys::RTCRay16, h: usize, n: usize) {
    let (lo, m) = (8 * h, n.saturating_sub(8 * h).min(8));
    if m == 0 {
        return;
    }
    if m < HALF_MIN {
        for k in lo..lo + m {
            let mut ray = rtc_ray(
                Vec3::new(p.org_x[k], p.org_y[k], p.org_z[k]),
                Vec3::new(p.dir_x[k], p.dir_y[k], p.dir_z[k]),
                p.tnear[k],
                p.tfar[k],
            );
            // SAFETY: the scene is committed; `ray` is a valid RTCRay.
            unsafe { sys::rtcOccluded1(scene, &mut ray, null_mut()) };
            p.tfar[k] = ray.tfar;
        }
        return;
    }
    let valid = Valid8::first(m);
    let mut r = half_of(p, lo);
    // SAFETY: a committed scene; `RTCRay8` and `Valid8` are 32-byte aligned as
    // rtcOccluded8 requires; lanes with valid = 0 are ignored.
    unsafe { sys::rtcOccluded8(valid.0.as_ptr(), scene, &mut r, null_mut()) };
    p.tfar[lo..lo + 8].copy_from_slice(&r.tfar);
}

// SAFETY: Embree documents committed scenes as safe to query concurrently, and the device
// and scene handles are reference-counted objects not tied to a thread.
unsafe impl Send for EmbreeScene {}
// SAFETY: as above; `&self` methods only run queries on the committed scene.
unsafe impl Sync for EmbreeScene {}

/// What the closest-hit query returns.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RawHit {
    /// Index of the triangle hit, in the order given to [`EmbreeScene::new`].
    pub prim: u32,
    /// Ray parameter of the hit (distance when the direction has unit length).
    pub t: f32,
    /// Barycentric coordinates of the hit in its triangle `(v0, v1, v2)`: the point is
    /// `(1 - u - v) v0 + u v1 + v v2`.
    pub u: f32,
    /// See `u`.
    pub v: f32,
    /// True when the ray met the side the triangle's winding normal points to.
    pub against: bool,
}

/// The valid mask of a 16-wide packet query, aligned like the packet.
#[repr(C, align(64))]
struct Valid16([i32; 16]);

/// `RTCRayHit` followed by spare room: Embree builds with instance arrays enabled write an
/// extra `instPrimID` after `instID`, which the 4.2 headers of `embree4-sys` do not declare.
#[repr(C, align(16))]
struct PaddedRayHit {
    rayhit: sys::RTCRayHit,
    _spare: [u32; 8],
}

/// Copies up to 16 origins and directions (structure of arrays, `org[0].len()` rays) into
/// the first lanes of a packet; a full packet's lanes are copied whole.
#[inline(always)]
fn load_lanes(r: &mut sys::RTCRay16, org: [&[f32]; 3], dir: [&[f32]; 3]) {
    let n = org[0].len();
    let lanes = [
        &mut r.org_x,
        &mut r.org_y,
        &mut r.org_z,
        &mut r.dir_x,
        &mut r.dir_y,
        &mut r.dir_z,
    ];
    for (lane, src) in lanes
        .into_iter()
        .zip([org[0], org[1], org[2], dir[0], dir[1], dir[2]])
    {
        if let Ok(full) = <&[f32; 16]>::try_from(src) {
            *lane = *full;
        } else {
            lane[..n].copy_from_slice(&src[..n]);
        }
    }
}

/// Sign of Embree's geometric normal `Ng` relative to the winding normal
/// `(v1 - v0) x (v2 - v0)` of a triangle (checked by `ng_sign_is_embree_convention`).
const NG_SIGN: f32 = 1.0;

/// `RTCRayHit16` with spare room after it, for the same reason as [`PaddedRayHit`]
/// (16 lanes of `instPrimID`).
#[repr(C, align(64))]
struct PaddedRayHit16 {
    rayhit: sys::RTCRayHit16,
    _spare: [u32; 32],
}

/// Storage of one 16-ray closest-hit packet, reused across
/// [`EmbreeScene::intersect16_soa`] calls (1.4 KB: set up once, not per packet).
pub struct HitPacket16(PaddedRayHit16);

impl HitPacket16 {
    /// A packet with the fields no query changes set: `time = 0`, all mask
    /// bits, `id = flags = 0`.
    pub fn new() -> HitPacket16 {
        let mut p = PaddedRayHit16 {
            rayhit: sys::RTCRayHit16 {
                ray: sys::RTCRay16::default(),
                hit: sys::RTCHit16::default(),
            },
            _spare: [u32::MAX; 32],
        };
        p.rayhit.ray.mask = [u32::MAX; 16];
        HitPacket16(p)
    }
}

impl HitPacket16 {
    /// Barycentric coordinates `(u, v)` of lane `k`'s hit after
    /// [`EmbreeScene::intersect16_soa`] (meaningful only where it reported a hit).
    #[inline(always)]
    pub fn uv(&self, k: usize) -> (f32, f32) {
        (self.0.rayhit.hit.u[k], self.0.rayhit.hit.v[k])
    }
}

impl Default for HitPacket16 {
    fn default() -> Self {
        HitPacket16::new()
    }
}

/// A reusable `RTCRay16` for [`EmbreeScene::free16_soa`]: made once per batch of
/// packets (a fresh 768-byte packet was filled for every 16 rays).
pub struct SegmentPacket16(sys::RTCRay16);

impl SegmentPacket16 {
    /// A fresh packet (`RTCRay16::default()`: `tnear = 0`, `time = 0`, every mask bit,
    /// `id = flags = 0`, fields no occlusion query changes).
    pub fn new() -> SegmentPacket16 {
        SegmentPacket16(sys::RTCRay16::default())
    }
}

impl Default for SegmentPacket16 {
    fn default() -> Self {
        SegmentPacket16::new()
    }
}

impl EmbreeScene {
    /// Builds and commits a scene from triangles (indices into `vertices`).
    pub fn new(vertices: &[Vec3], triangles: &[[u32; 3]]) -> Result<Self, Error> {
        if triangles.len() > u32::MAX as usize / 2 || vertices.len() > u32::MAX as usize / 2 {
            return Err(Error::Embree(
                "mesh too large for one Embree geometry".into(),
            ));
        }
        let config = c"threads=0,verbose=0";
        // SAFETY: `rtcNewDevice` accepts a NUL-terminated configuration string.
        let device = unsafe { sys::rtcNewDevice(config.as_ptr()) };
        if device.is_null() {
            return Err(Error::Embree(
                "rtcNewDevice failed (CPU without SSE2, or a broken libembree4)".into(),
            ));
        }
        let sink = Box::new(ErrorSink {
            last: Mutex::new(None),
        });
        // SAFETY: the sink is boxed (stable address) and outlives the device (see Drop).
        unsafe {
            sys::rtcSetDeviceErrorFunction(
                device,
                Some(error_callback),
                &*sink as *const ErrorSink as *mut c_void,
            )
        };
        // SAFETY: a valid device; a null scene is reported below.
        let scene = unsafe { sys::rtcNewScene(device) };
        // SAFETY: a valid device; NATIVE_RAY16_SUPPORTED is a read-only property.
        let native16 = unsafe {
            sys::rtcGetDeviceProperty(device, sys::RTCDeviceProperty::NATIVE_RAY16_SUPPORTED)
        } != 0;
        let mut this = EmbreeScene {
            device,
            scene,
            sink,
            wide16: native16,
        };
        if scene.is_null() {
            return Err(this.error("rtcNewScene"));
        }
        this.add_triangles(vertices, triangles)?;
        // SAFETY: the scene is valid and in its build phase.
        unsafe {
            sys::rtcSetSceneBuildQuality(this.scene, sys::RTCBuildQuality::HIGH);
            sys::rtcSetSceneFlags(this.scene, sys::RTCSceneFlags::ROBUST);
            sys::rtcCommitScene(this.scene);
        }
        this.check("rtcCommitScene")?;
        Ok(this)
    }

    fn add_triangles(&mut self, vertices: &[Vec3], triangles: &[[u32; 3]]) -> Result<(), Error> {
        // SAFETY: a valid device.
        let geom = unsafe { sys::rtcNewGeometry(self.device, sys::RTCGeometryType::TRIANGLE) };
        if geom.is_null() {
            return Err(self.error("rtcNewGeometry"));
        }
        // SAFETY: Embree allocates `itemCount * byteStride` bytes (plus padding) and returns
        // a pointer valid until the geometry is released; we write exactly that many items.
        unsafe {
            let vb = sys::rtcSetNewGeometryBuffer(
                geom,
                sys::RTCBufferType::VERTEX,
                0,
                sys::RTCFormat::FLOAT3,
                12,
                vertices.len(),
            ) as *mut f32;
            let ib = sys::rtcSetNewGeometryBuffer(
                geom,
                sys::RTCBufferType::INDEX,
                0,
                sys::RTCFormat::UINT3,
                12,
                triangles.len(),
            ) as *mut u32;
            if vb.is_null() || ib.is_null() {
                sys::rtcReleaseGeometry(geom);
                return Err(self.error("rtcSetNewGeometryBuffer"));
            }
            // The buffers are uninitialised memory: no slice or reference is made over
            // them; each item is written through the raw pointer (`ptr::write` of an
            // `f32`/`u32`, 4-byte aligned as Embree's buffers are 16-byte aligned).
            for (k, v) in vertices.iter().enumerate() {
                for (c, x) in [v.x, v.y, v.z].into_iter().enumerate() {
                    vb.add(3 * k + c).write(x);
                }
            }
            for (k, t) in triangles.iter().enumerate() {
                for (c, &x) in t.iter().enumerate() {
                    ib.add(3 * k + c).write(x);
                }
            }
            sys::rtcCommitGeometry(geom);
            sys::rtcAttachGeometry(self.scene, geom);
            sys::rtcReleaseGeometry(geom);
        }
        self.check("building the triangle geometry")
    }

    /// The Embree version the library reports, as `major.minor.patch`.
    pub fn version(&self) -> String {
        // SAFETY: a valid device; VERSION is a read-only property.
        let v = unsafe { sys::rtcGetDeviceProperty(self.device, sys::RTCDeviceProperty::VERSION) };
        format!("{}.{}.{}", v / 10000, (v / 100) % 100, v % 100)
    }

    fn error(&self, what: &str) -> Error {
        let msg = self.sink.last.lock().ok().and_then(|mut l| l.take());
        // SAFETY: a valid device.
        let code = unsafe { sys::rtcGetDeviceError(self.device) };
        Error::Embree(format!(
            "{what} failed: {}",
            msg.unwrap_or_else(|| format!("{code:?}"))
        ))
    }

    fn check(&self, what: &str) -> Result<(), Error> {
        // SAFETY: a valid device; reading the error also clears it.
        let code = unsafe { sys::rtcGetDeviceError(self.device) };
        let msg = self.sink.last.lock().ok().and_then(|mut l| l.take());
        if code == sys::RTCError::NONE && msg.is_none() {
            Ok(())
        } else {
            Err(Error::Embree(format!(
                "{what} failed: {}",
                msg.unwrap_or_else(|| format!("{code:?}"))
            )))
        }
    }

    /// True when something lies on the ray between `tnear` and `tfar`.
    #[inline]
    pub fn occluded1(&self, org: Vec3, dir: Vec3, tnear: f32, tfar: f32) -> bool {
        let mut ray = rtc_ray(org, dir, tnear, tfar);
        // SAFETY: the scene is committed; `ray` is a valid RTCRay; null arguments are allowed.
        unsafe { sys::rtcOccluded1(self.scene, &mut ray, null_mut()) };
        // Embree sets tfar to -inf on an occluded ray.
        ray.tfar < 0.0
    }

    /// [`EmbreeScene::occluded16`] of segment rays `(origin, direction, tfar)`, all from
    /// `tnear`, filled straight into the packet.
    #[inline]
    pub fn occluded16_segments(&self, rays: &[(Vec3, Vec3, f32)], tnear: f32, out: &mut [bool]) {
        self.occluded16_with(
            rays.len(),
            |k| (rays[k].0, rays[k].1, tnear, rays[k].2),
            out,
        );
    }

    /// `rtcOccluded16` over up to 16 segment rays given as structure of arrays: ray k
    /// starts at `(org[0][k], org[1][k], org[2][k])`, has direction `dir[.][k]` and runs
    /// over `[tnear, tfar]`. The slices are copied into the packet whole (no transposition);
    /// `out[k]` is set to true when nothing blocks ray k (written once, as the answer: a
    /// second pass inverting a blocked flag read the 16 bytes back as one load right after
    /// their 16 one-byte stores, which the store buffer cannot forward).
    /// The packet `p` is reused: a full one has every per-ray field it reads written here
    /// (origins, directions, `tnear`, `tfar`; occlusion changes nothing else), and a partial one is
    /// made fresh first, so every query sees the packet a fresh one would be.
    #[inline(always)]
    pub fn free16_soa(
        &self,
        p: &mut SegmentPacket16,
        org: [&[f32]; 3],
        dir: [&[f32]; 3],
        tnear: f32,
        tfar: f32,
        out: &mut [bool],
    ) {
        let n = org[0].len();
        debug_assert!(n <= 16 && out.len() >= n);
        if n < 16 {
            *p = SegmentPacket16::new();
        }
        let packet = &mut p.0;
        let mut valid = Valid16([0i32; 16]);
        valid.0[..n].fill(-1);
        load_lanes(packet, org, dir);
        packet.tnear[..n].fill(tnear);
        packet.tfar[..n].fill(tfar);
        if self.wide16 {
            // SAFETY: as in `occluded16_with`: committed scene, 64-byte aligned packet and
            // mask, lanes with valid = 0 ignored.
            unsafe { sys::rtcOccluded16(valid.0.as_ptr(), self.scene, packet, null_mut()) };
        } else {
            occluded_half(self.scene, packet, 0, n);
            occluded_half(self.scene, packet, 1, n);
        }
        // Embree sets tfar to -inf on an occluded ray and leaves the others' (`tfar > 0`).
        for (o, tfar) in out.iter_mut().zip(packet.tfar).take(n) {
            *o = tfar >= 0.0;
        }
    }

    /// Occlusion for up to 16 rays at once (`rtcOccluded16`). Each ray is
    /// `(origin, direction, tnear, tfar)`; `out[k]` is set to true when ray k is blocked.
    #[inline(always)]
    pub fn occluded16(&self, rays: &[(Vec3, Vec3, f32, f32)], out: &mut [bool]) {
        self.occluded16_with(rays.len(), |k| rays[k], out);
    }

    /// One `rtcOccluded16` over `n <= 16` rays given by `ray(k)`.
    #[inline(always)]
    fn occluded16_with(
        &self,
        n: usize,
        ray: impl Fn(usize) -> (Vec3, Vec3, f32, f32),
        out: &mut [bool],
    ) {
        debug_assert!(n <= 16 && out.len() >= n);
        let mut packet = sys::RTCRay16::default();
        debug_assert_eq!(std::ptr::addr_of!(packet) as usize % 64, 0);
        let mut valid = Valid16([0i32; 16]);
        for k in 0..n.min(16) {
            let (o, d, tn, tf) = ray(k);
            valid.0[k] = -1;
            packet.org_x[k] = o.x;
            packet.org_y[k] = o.y;
            packet.org_z[k] = o.z;
            packet.dir_x[k] = d.x;
            packet.dir_y[k] = d.y;
            packet.dir_z[k] = d.z;
            packet.tnear[k] = tn;
            packet.tfar[k] = tf;
        }
        // SAFETY: the scene is committed; the packet and the valid mask are 64-byte aligned
        // as rtcOccluded16 requires (bindgen keeps RTC_ALIGN(64) on RTCRay16, checked by the
        // `packet_types_are_64_byte_aligned` test; `Valid16` is aligned by hand); lanes with
        // valid = 0 are ignored.
        if self.wide16 {
            unsafe { sys::rtcOccluded16(valid.0.as_ptr(), self.scene, &mut packet, null_mut()) };
        } else {
            occluded_half(self.scene, &mut packet, 0, n);
            occluded_half(self.scene, &mut packet, 1, n);
        }
        for (o, tfar) in out.iter_mut().zip(packet.tfar).take(n) {
            *o = tfar < 0.0;
        }
    }

    /// Closest hits of up to 16 rays at once (`rtcIntersect16`), given as structure of
    /// arrays (ray k from `(org[0][k], org[1][k], org[2][k])` along `dir[.][k]`, over
    /// `[tnear, inf)`) and traced in the reusable packet `p`: `out[k]` is the triangle ray k
    /// hits first, or `u32::MAX`, and `against[k]` is true when the ray meets that
    /// triangle against its winding normal `(v1 - v0) x (v2 - v0)` (from the side the
    /// normal points to). Full packets are copied in whole; only the fields a query
    /// changes are reset.
    #[inline(always)]
    pub fn intersect16_soa(
        &self,
        p: &mut HitPacket16,
        org: [&[f32]; 3],
        dir: [&[f32]; 3],
        tnear: f32,
        out: &mut [u32],
        against: &mut [bool],
    ) {
        let n = org[0].len();
        debug_assert!(n <= 16 && out.len() >= n && against.len() >= n);
        let mut valid = Valid16([0i32; 16]);
        valid.0[..n].fill(-1);
        let rh = &mut p.0.rayhit;
        let r = &mut rh.ray;
        load_lanes(r, org, dir);
        r.tnear = [tnear; 16];
        r.tfar = [f32::INFINITY; 16];
        rh.hit.geomID = [sys::RTC_INVALID_GEOMETRY_ID; 16];
        // SAFETY: the scene is committed; the ray-hit packet and the mask are 64-byte
        // aligned (`PaddedRayHit16`, `Valid16`), with room after the hit for the widest
        // RTCHit16 layout; lanes with valid = 0 are ignored.
        if self.wide16 {
            unsafe { sys::rtcIntersect16(valid.0.as_ptr(), self.scene, rh, null_mut()) };
        } else {
            self.intersect_half(rh, 0, n);
            self.intersect_half(rh, 1, n);
        }
        let (hit, r) = (&rh.hit, &rh.ray);
        for k in 0..n {
            out[k] = if hit.geomID[k] != sys::RTC_INVALID_GEOMETRY_ID {
                hit.primID[k]
            } else {
                u32::MAX
            };
            // Embree's Ng is `(v1 - v0) x (v2 - v0)` scaled by NG_SIGN.
            let d = hit.Ng_x[k] * r.dir_x[k] + hit.Ng_y[k] * r.dir_y[k] + hit.Ng_z[k] * r.dir_z[k];
            against[k] = d * NG_SIGN < 0.0;
        }
    }

    /// How 16-ray packets are traced on this machine.
    pub fn packet_width(&self) -> PacketWidth {
        if self.wide16 {
            PacketWidth::Sixteen
        } else {
            PacketWidth::Eight
        }
    }

    /// Traces 16-ray packets as `w` from now on (the answers are the same).
    pub fn set_packet_width(&mut self, w: PacketWidth) {
        self.wide16 = w == PacketWidth::Sixteen;
    }

    /// Traces lanes `[8h, 8h + 8)` of a 16-wide closest-hit packet as one
    /// `rtcIntersect8` and writes back the hit fields the caller reads.
    #[inline(always)]
    fn intersect_half(&self, rh: &mut sys::RTCRayHit16, h: usize, n: usize) {
        let (lo, m) = (8 * h, n.saturating_sub(8 * h).min(8));
        if m == 0 {
            return;
        }
        let valid = Valid8::first(m);
        let mut q = PaddedRayHit8 {
            rayhit: sys::RTCRayHit8 {
                ray: half_of(&rh.ray, lo),
                hit: sys::RTCHit8 {
                    geomID: [sys::RTC_INVALID_GEOMETRY_ID; 8],
                    ..Default::default()
                },
            },
            _spare: [u32::MAX; 16],
        };
        // SAFETY: a committed scene; the ray-hit packet and the mask are 32-byte aligned
        // (`PaddedRayHit8`, `Valid8`), with room after the hit for the widest RTCHit8
        // layout; lanes with valid = 0 are ignored.
        unsafe { sys::rtcIntersect8(valid.0.as_ptr(), self.scene, &mut q.rayhit, null_mut()) };
        let (hit, ray) = (&q.rayhit.hit, &q.rayhit.ray);
        let o = &mut rh.hit;
        o.geomID[lo..lo + 8].copy_from_slice(&hit.geomID);
        o.primID[lo..lo + 8].copy_from_slice(&hit.primID);
        o.u[lo..lo + 8].copy_from_slice(&hit.u);
        o.v[lo..lo + 8].copy_from_slice(&hit.v);
        o.Ng_x[lo..lo + 8].copy_from_slice(&hit.Ng_x);
        o.Ng_y[lo..lo + 8].copy_from_slice(&hit.Ng_y);
        o.Ng_z[lo..lo + 8].copy_from_slice(&hit.Ng_z);
        rh.ray.tfar[lo..lo + 8].copy_from_slice(&ray.tfar);
    }

    /// The closest hit along the ray in `[tnear, tfar]`, if any.
    #[inline]
    pub fn intersect1(&self, org: Vec3, dir: Vec3, tnear: f32, tfar: f32) -> Option<RawHit> {
        let mut rh = PaddedRayHit {
            rayhit: sys::RTCRayHit {
                ray: rtc_ray(org, dir, tnear, tfar),
                hit: sys::RTCHit::default(),
            },
            _spare: [u32::MAX; 8],
        };
        // SAFETY: the scene is committed; the ray-hit has room for the widest RTCHit layout.
        unsafe { sys::rtcIntersect1(self.scene, &mut rh.rayhit, null_mut()) };
        let hit = &rh.rayhit.hit;
        let d = hit.Ng_x * dir.x + hit.Ng_y * dir.y + hit.Ng_z * dir.z;
        (hit.geomID != sys::RTC_INVALID_GEOMETRY_ID).then_some(RawHit {
            prim: hit.primID,
            t: rh.rayhit.ray.tfar,
            u: hit.u,
            v: hit.v,
            against: d * NG_SIGN < 0.0,
        })
    }
}

/// One ray from `org` along `dir` over `[tnear, tfar]`, every mask bit set.
#[inline]
fn rtc_ray(org: Vec3, dir: Vec3, tnear: f32, tfar: f32) -> sys::RTCRay {
    sys::RTCRay {
        org_x: org.x,
        org_y: org.y,
        org_z: org.z,
        tnear,
        dir_x: dir.x,
        dir_y: dir.y,
        dir_z: dir.z,
        time: 0.0,
        tfar,
        mask: u32::MAX,
        id: 0,
        flags: 0,
    }
}

/// Sets flush-to-zero and denormals-are-zero (MXCSR bits 15 and 6) on the calling thread,
/// as the Embree documentation recommends for every thread that traces rays. Returns false
/// where there is no MXCSR (not x86-64). Only denormal results and inputs change (to 0).
pub fn flush_denormals() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        let mut csr: u32 = 0;
        // SAFETY: `stmxcsr`/`ldmxcsr` read and write the thread's own SSE control register
        // through a valid, aligned u32; setting FTZ and DAZ raises no exception and leaves
        // the rounding mode and exception masks as they were.
        unsafe {
            std::arch::asm!("stmxcsr [{}]", in(reg) &mut csr as *mut u32, options(nostack));
            csr |= (1 << 15) | (1 << 6);
            std::arch::asm!("ldmxcsr [{}]", in(reg) &csr as *const u32, options(nostack, readonly));
        }
        true
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

impl Drop for EmbreeScene {
    fn drop(&mut self) {
        // SAFETY: handles created in `new` and released once here; the scene before the
        // device, and the error sink only after the device is gone.
        unsafe {
            if !self.scene.is_null() {
                sys::rtcReleaseScene(self.scene);
            }
            sys::rtcReleaseDevice(self.device);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packet_types_are_64_byte_aligned() {
        assert_eq!(std::mem::align_of::<sys::RTCRay16>(), 64);
        assert_eq!(std::mem::align_of::<Valid16>(), 64);
    }

    #[test]
    fn packet_and_single_queries_agree() {
        // A unit square in z = 0 and rays crossing it or not.
        let v = [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
        ];
        let scene = EmbreeScene::new(&v, &[[0, 1, 2], [0, 2, 3]]).unwrap();
        let rays: Vec<(Vec3, Vec3, f32, f32)> = (0..13)
            .map(|k| {
                let x = -0.5 + 0.17 * k as f32;
                (Vec3::new(x, 0.5, 1.0), Vec3::new(0.0, 0.0, -2.0), 0.0, 1.0)
            })
            .collect();
        let mut scene = scene;
        for w in [PacketWidth::Sixteen, PacketWidth::Eight] {
            scene.set_packet_width(w);
            // 13 rays (a full half and 5 rays, traced one by one where halves are 8-wide),
            // 7 (one partly filled 8-wide half) and 5.
            for n in [13, 7, 5] {
                let mut out = [false; 16];
                scene.occluded16(&rays[..n], &mut out);
                let (mut free, mut p) = ([true; 16], SegmentPacket16::new());
                let col = |f: fn(&(Vec3, Vec3, f32, f32)) -> f32| {
                    rays[..n].iter().map(f).collect::<Vec<f32>>()
                };
                let (ox, oy, oz) = (col(|r| r.0.x), col(|r| r.0.y), col(|r| r.0.z));
                let (dx, dy, dz) = (col(|r| r.1.x), col(|r| r.1.y), col(|r| r.1.z));
                scene.free16_soa(
                    &mut p,
                    [&ox, &oy, &oz],
                    [&dx, &dy, &dz],
                    0.0,
                    1.0,
                    &mut free,
                );
                for (k, r) in rays[..n].iter().enumerate() {
                    let single = scene.occluded1(r.0, r.1, r.2, r.3);
                    assert_eq!(out[k], single, "{w}, n = {n}, ray {k}");
                    assert_eq!(free[k], !single, "{w}, n = {n}, ray {k}");
                }
                // Some rays of each half cross the square, some miss it.
                assert!(out[..n.min(8)].contains(&true) && out[..n.min(8)].contains(&false));
            }
        }
        assert!(flush_denormals() || cfg!(not(target_arch = "x86_64")));
    }

    /// `intersect16_soa` reports hits against the winding normal: from above for a
    /// triangle counter-clockwise seen from above, from below for the same triangle wound
    /// the other way; and agrees with `intersect1` on what is hit.
    #[test]
    fn ng_sign_is_embree_convention() {
        let v = [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
            Vec3::new(0.0, 0.0, -1.0),
            Vec3::new(1.0, 0.0, -1.0),
            Vec3::new(0.0, 1.0, -1.0),
        ];
        // Triangle 0 (z = 0): normal +z. Triangle 1 (z = -1): wound clockwise, normal -z.
        let mut scene = EmbreeScene::new(&v, &[[0, 1, 2], [3, 5, 4]]).unwrap();
        for (w, n) in [PacketWidth::Sixteen, PacketWidth::Eight]
            .into_iter()
            .flat_map(|w| [1, 5, 12, 16].map(|n| (w, n)))
        {
            scene.set_packet_width(w);
            let org: Vec<[f32; 3]> = (0..n)
                .map(|k| {
                    [
                        0.2 + 0.01 * k as f32,
                        0.3,
                        if k % 2 == 0 { 1.0 } else { -2.0 },
                    ]
                })
                .collect();
            let dir: Vec<[f32; 3]> = (0..n)
                .map(|k| [0.0, 0.0, if k % 2 == 0 { -1.0 } else { 1.0 }])
                .collect();
            let col = |a: &[[f32; 3]], c: usize| a.iter().map(|p| p[c]).collect::<Vec<f32>>();
            let (ox, oy, oz) = (col(&org, 0), col(&org, 1), col(&org, 2));
            let (dx, dy, dz) = (col(&dir, 0), col(&dir, 1), col(&dir, 2));
            let (mut out, mut against) = ([0u32; 16], [false; 16]);
            let mut p = HitPacket16::new();
            scene.intersect16_soa(
                &mut p,
                [&ox, &oy, &oz],
                [&dx, &dy, &dz],
                0.0,
                &mut out,
                &mut against,
            );
            for k in 0..n {
                let o = Vec3::from(org[k]);
                let d = Vec3::from(dir[k]);
                let one = scene.intersect1(o, d, 0.0, f32::INFINITY).unwrap();
                assert_eq!(out[k], one.prim, "{w}, n = {n}, ray {k}");
                assert_eq!(one.against, against[k], "{w}, n = {n}, ray {k}");
                // Barycentrics: triangle 0 is (0,0,0), (1,0,0), (0,1,0), so u = x and v = y;
                // triangle 1 is (0,0,-1), (0,1,-1), (1,0,-1), so u = y and v = x.
                let (u, v) = p.uv(k);
                assert!(
                    (u - one.u).abs() < 1e-6 && (v - one.v).abs() < 1e-6,
                    "{w} {n} {k}"
                );
                let (x, y) = if k % 2 == 0 { (u, v) } else { (v, u) };
                assert!(
                    (x - o.x).abs() < 1e-6 && (y - o.y).abs() < 1e-6,
                    "{w} {n} {k}"
                );
                // Down from z = 1: hits triangle 0 from the side of its normal (+z).
                // Up from z = -2: hits triangle 1 from the side of its normal (-z).
                assert!(against[k], "{w}, n = {n}, ray {k}");
            }
        }
        // And from the back: up from z = -0.5 into triangle 0, along its normal.
        let (mut out, mut against) = ([0u32; 16], [true; 16]);
        let mut p = HitPacket16::new();
        scene.intersect16_soa(
            &mut p,
            [&[0.2], &[0.3], &[-0.5]],
            [&[0.0], &[0.0], &[1.0]],
            0.0,
            &mut out,
            &mut against,
        );
        assert_eq!(out[0], 0);
        assert!(!against[0]);
    }
}
