//! The only `unsafe` code in the crate: a small safe layer over `embree4-sys`.
//!
//! `embree4-rs` 0.0.16 has no occlusion query and keeps its scene handle private, so this
//! module talks to the C API directly: a device, one committed triangle scene, occlusion
//! (`rtcOccluded1`, `rtcOccluded16`) and closest-hit (`rtcIntersect1`) queries, and Embree
//! errors turned into [`Error::Embree`].
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
    triangles: usize,
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
}

/// `RTCRayHit` followed by spare room: Embree builds with instance arrays enabled write an
/// extra `instPrimID` after `instID`, which the 4.2 headers of `embree4-sys` do not declare.
#[repr(C, align(16))]
struct PaddedRayHit {
    rayhit: sys::RTCRayHit,
    _spare: [u32; 8],
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
        let mut this = EmbreeScene {
            device,
            scene,
            sink,
            triangles: triangles.len(),
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
            let vs = std::slice::from_raw_parts_mut(vb, vertices.len() * 3);
            for (k, v) in vertices.iter().enumerate() {
                vs[3 * k..3 * k + 3].copy_from_slice(&[v.x, v.y, v.z]);
            }
            let is = std::slice::from_raw_parts_mut(ib, triangles.len() * 3);
            for (k, t) in triangles.iter().enumerate() {
                is[3 * k..3 * k + 3].copy_from_slice(t);
            }
            sys::rtcCommitGeometry(geom);
            sys::rtcAttachGeometry(self.scene, geom);
            sys::rtcReleaseGeometry(geom);
        }
        self.check("building the triangle geometry")
    }

    /// Number of triangles in the scene.
    pub fn triangle_count(&self) -> usize {
        self.triangles
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
        let mut ray = sys::RTCRay {
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
        };
        // SAFETY: the scene is committed; `ray` is a valid RTCRay; null arguments are allowed.
        unsafe { sys::rtcOccluded1(self.scene, &mut ray, null_mut()) };
        // Embree sets tfar to -inf on an occluded ray.
        ray.tfar < 0.0
    }

    /// Occlusion for up to 16 rays at once (`rtcOccluded16`). Each ray is
    /// `(origin, direction, tnear, tfar)`; `out[k]` is set to true when ray k is blocked.
    pub fn occluded16(&self, rays: &[(Vec3, Vec3, f32, f32)], out: &mut [bool]) {
        debug_assert!(rays.len() <= 16 && out.len() >= rays.len());
        let mut packet = sys::RTCRay16::default();
        let mut valid = [0i32; 16];
        for (k, (o, d, tn, tf)) in rays.iter().enumerate() {
            valid[k] = -1;
            packet.org_x[k] = o.x;
            packet.org_y[k] = o.y;
            packet.org_z[k] = o.z;
            packet.dir_x[k] = d.x;
            packet.dir_y[k] = d.y;
            packet.dir_z[k] = d.z;
            packet.tnear[k] = *tn;
            packet.tfar[k] = *tf;
        }
        // SAFETY: the scene is committed; the packet is 64-byte aligned as RTCRay16 requires
        // (bindgen keeps RTC_ALIGN(64)); lanes with valid = 0 are ignored.
        unsafe { sys::rtcOccluded16(valid.as_ptr(), self.scene, &mut packet, null_mut()) };
        for (o, tfar) in out.iter_mut().zip(packet.tfar).take(rays.len()) {
            *o = tfar < 0.0;
        }
    }

    /// The closest hit along the ray in `[tnear, tfar]`, if any.
    #[inline]
    pub fn intersect1(&self, org: Vec3, dir: Vec3, tnear: f32, tfar: f32) -> Option<RawHit> {
        let mut rh = PaddedRayHit {
            rayhit: sys::RTCRayHit {
                ray: sys::RTCRay {
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
                },
                hit: sys::RTCHit::default(),
            },
            _spare: [u32::MAX; 8],
        };
        // SAFETY: the scene is committed; the ray-hit has room for the widest RTCHit layout.
        unsafe { sys::rtcIntersect1(self.scene, &mut rh.rayhit, null_mut()) };
        let hit = &rh.rayhit.hit;
        (hit.geomID != sys::RTC_INVALID_GEOMETRY_ID).then_some(RawHit {
            prim: hit.primID,
            t: rh.rayhit.ray.tfar,
        })
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
