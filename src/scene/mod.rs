//! Scenes: polygons with diffuse materials, as loaded from OBJ/MTL or built in.
//!
//! A [`Scene`] is what the user described, cleaned: planar convex polygons of 3 or 4
//! vertices (any other simple polygon is meshed as written into triangles covering exactly
//! its area, well shaped for the patch mesher: see [`polygon`]), each with a
//! [`Material`] holding the RGB reflectance `rho` (MTL `Kd`, each channel in [0, 1)) and the
//! RGB emission `emit` (MTL `Ke`, exitance units, >= 0), and to an object: a name of
//! [`Scene::objects`] (the OBJ `o` or `g` statement in force, see [`obj`]), which every
//! patch, table row and output node made from the face keeps. Nothing here knows about
//! patches or rays: the `mesh` module turns a scene into patches.

pub mod builtin;
pub mod coincident;
pub mod generated;
pub mod obj;
pub mod polygon;

use glam::{DVec2, DVec3, Vec3};

use crate::error::{Error, Result};

/// Largest emission accepted: the radiosity, up to `E / (1 - rho)`, is written as f32
/// (largest about 3.4e38), and rho may be as close to 1 as 1 - 1e-8.
pub const MAX_EMIT: f64 = 1e30;

/// Rec. 709 luminance of linear RGB (ITU-R BT.709-6, item 3.2): the one scalar every
/// report, chart and preview exposure uses for a colour.
pub fn luminance(c: [f64; 3]) -> f64 {
    0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]
}

/// A diffuse material: reflectance and emitted exitance per RGB channel.
#[derive(Clone, Debug, PartialEq)]
pub struct Material {
    /// Name from the MTL file.
    pub name: String,
    /// Reflectance per channel, in [0, 1).
    pub rho: [f64; 3],
    /// Emitted exitance per channel (radiosity units), >= 0.
    pub emit: [f64; 3],
    /// Gray emissivity and boundary condition of the thermal mode (MTL `#@thermal`, or a
    /// boundary-conditions file); `None` when the material has none. The visible-light
    /// bake ignores it.
    pub thermal: Option<Thermal>,
    /// Two-sided (MTL `#@two-sided`): every face of the material emits, receives and
    /// reflects on both sides, as two faces back to back ([`Scene::make_two_sided`]).
    pub two_sided: bool,
}

/// Upper bound on a boundary temperature, K (far above any gray-surface problem; keeps
/// `sigma T^4` and its sums far from overflow).
pub const MAX_TEMPERATURE: f64 = 1e6;

/// Upper bound on the magnitude of a boundary net flux, W/m².
pub const MAX_FLUX: f64 = 1e15;

/// The boundary condition of a surface in the thermal mode.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Boundary {
    /// A given temperature, K.
    Temperature(f64),
    /// A given net radiative flux leaving the surface, W/m² (`q = J - G`; 0 is an adiabatic,
    /// re-radiating surface).
    Flux(f64),
}

/// Thermal properties of an opaque gray diffuse surface: emissivity `eps` in (0, 1], so
/// that by Kirchhoff's law the absorptance is `eps` and the reflectance `1 - eps`
/// (radiosidade.md, "Emissividade", "Lei de Kirchhoff"; Modest, *Radiative Heat Transfer*,
/// 3rd ed., sec. 1.6 and 6.2), and its boundary condition.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Thermal {
    /// Hemispherical total emissivity, in (0, 1].
    pub emissivity: f64,
    /// Given temperature or net flux.
    pub boundary: Boundary,
}

impl Thermal {
    /// Checks the ranges: `eps` in (0, 1], a temperature in `[0, MAX_TEMPERATURE]`, a
    /// finite flux of magnitude at most [`MAX_FLUX`]. Returns what is wrong, for the
    /// caller to wrap with the file and line.
    pub fn validate(&self) -> std::result::Result<(), String> {
        let e = self.emissivity;
        if !(e.is_finite() && e > 0.0 && e <= 1.0) {
            return Err(format!(
                "emissivity {e} is outside (0, 1] (a gray opaque surface absorbs eps and \
                 reflects 1 - eps; eps = 0 would leave its temperature undefined)"
            ));
        }
        match self.boundary {
            Boundary::Temperature(t)
                if !(t.is_finite() && (0.0..=MAX_TEMPERATURE).contains(&t)) =>
            {
                Err(format!(
                    "temperature {t} K is outside [0, {MAX_TEMPERATURE:e}] K"
                ))
            }
            Boundary::Flux(q) if !(q.is_finite() && q.abs() <= MAX_FLUX) => Err(format!(
                "net flux {q} W/m^2 is not a finite number of magnitude at most {MAX_FLUX:e}"
            )),
            _ => Ok(()),
        }
    }
}

impl Material {
    /// True when the material emits in any channel.
    pub fn is_emitter(&self) -> bool {
        self.emit.iter().any(|&e| e > 0.0)
    }

    /// Checks the physical ranges: `rho` in [0, 1) and finite non-negative `emit`.
    /// Returns what is wrong, for the caller to wrap with the file and line.
    pub fn validate(&self) -> std::result::Result<(), String> {
        for (c, &r) in self.rho.iter().enumerate() {
            if !r.is_finite() || !(0.0..1.0).contains(&r) {
                return Err(format!(
                    "reflectance Kd channel {} is {r}, outside [0, 1) (rho = 1 conserves all \
                     light and makes a closed scene singular)",
                    ["R", "G", "B"][c]
                ));
            }
        }
        for (c, &e) in self.emit.iter().enumerate() {
            if !e.is_finite() || e < 0.0 {
                return Err(format!(
                    "emission Ke channel {} is {e}, must be finite and >= 0",
                    ["R", "G", "B"][c]
                ));
            }
            if e > MAX_EMIT {
                return Err(format!(
                    "emission Ke channel {} is {e:e}, above {MAX_EMIT:e}: the radiosity \
                     (up to E / (1 - rho)) is stored as f32 and would overflow",
                    ["R", "G", "B"][c]
                ));
            }
        }
        Ok(())
    }
}

/// A planar convex polygon of the scene (3 or 4 corners): an input face, or one triangle
/// of an input polygon meshed by [`polygon::mesh`] (all its triangles keep its line).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Face {
    /// Indices into [`Scene::positions`]; the 4th is [`Face::NONE`] for a triangle.
    pub corners: [u32; 4],
    /// Index into [`Scene::materials`].
    pub material: u32,
    /// Index into [`Scene::objects`].
    pub object: u32,
    /// 1-based line of the OBJ file that defined the face (0 when generated).
    pub line: u32,
    /// Texture coordinates of the corners, as indices into [`Scene::uvs`] (OBJ `vt`), in
    /// the order of `corners`; all [`Face::NONE`] when the face has none.
    pub uv: [u32; 4],
    /// The face's other side, for a two-sided surface ([`Scene::make_two_sided`]): the
    /// index of the face with the same corners wound the other way; [`Face::NONE`] for a
    /// one-sided face.
    pub twin: u32,
    /// True for the side [`Scene::make_two_sided`] added: the back of the face as written.
    pub back: bool,
}

impl Face {
    /// Marks the missing 4th corner of a triangle.
    pub const NONE: u32 = u32::MAX;

    /// Number of corners (3 or 4).
    pub fn len(&self) -> usize {
        if self.corners[3] == Self::NONE {
            3
        } else {
            4
        }
    }

    /// Always false: a face has at least three corners.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// The corner indices actually used.
    pub fn corner_slice(&self) -> &[u32] {
        &self.corners[..self.len()]
    }

    /// A face with these corners, material, object and line, without texture coordinates
    /// and one-sided.
    pub fn new(corners: [u32; 4], material: u32, object: u32, line: u32) -> Face {
        Face {
            corners,
            material,
            object,
            line,
            uv: [Face::NONE; 4],
            twin: Face::NONE,
            back: false,
        }
    }

    /// True when every corner has texture coordinates.
    pub fn has_uv(&self) -> bool {
        self.uv[..self.len()].iter().all(|&u| u != Face::NONE)
    }

    /// True when the face is one side of a two-sided surface.
    pub fn is_two_sided(&self) -> bool {
        self.twin != Face::NONE
    }
}

/// A length unit of scene coordinates: what a `#@units` line (or `--units`) names, so
/// that outputs in metres (glTF) can be scaled.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Units {
    /// Millimetres (`mm`).
    Millimetres,
    /// Centimetres (`cm`).
    Centimetres,
    /// Metres (`m`).
    Metres,
}

impl Units {
    /// The unit named `mm`, `cm` or `m`.
    pub fn parse(s: &str) -> Option<Units> {
        match s {
            "mm" => Some(Units::Millimetres),
            "cm" => Some(Units::Centimetres),
            "m" => Some(Units::Metres),
            _ => None,
        }
    }

    /// The short name: `mm`, `cm` or `m`.
    pub fn symbol(self) -> &'static str {
        match self {
            Units::Millimetres => "mm",
            Units::Centimetres => "cm",
            Units::Metres => "m",
        }
    }

    /// Metres in one unit.
    pub fn metres(self) -> f64 {
        match self {
            Units::Millimetres => 1e-3,
            Units::Centimetres => 1e-2,
            Units::Metres => 1.0,
        }
    }
}

/// A pinhole camera for previews.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Eye position.
    pub eye: Vec3,
    /// Point looked at.
    pub target: Vec3,
    /// Up direction.
    pub up: Vec3,
    /// Vertical field of view in degrees.
    pub vfov_deg: f32,
}

impl Camera {
    /// A camera that frames an axis-aligned box, looking along -z from in front of it
    /// (or along the box's thinnest axis when that is clearer).
    pub fn framing(lo: Vec3, hi: Vec3) -> Camera {
        let center = (lo + hi) * 0.5;
        let ext = (hi - lo).max(Vec3::splat(1e-6));
        let vfov_deg = 40.0f32;
        let radius = ext.length() * 0.5;
        let dist = radius / (vfov_deg.to_radians() * 0.5).tan() * 1.05;
        // Look from a direction slightly above and to the side, so that boxes show depth.
        let dir = Vec3::new(0.35, 0.45, 1.0).normalize();
        Camera {
            eye: center + dir * dist,
            target: center,
            up: Vec3::Y,
            vfov_deg,
        }
    }
}

/// The tilt of [`Scene::interior_camera`]'s probe rays off the grid directions.
const TILT: DVec3 = DVec3::new(0.0123, 0.0071, 0.0037);

/// A scene: positions, faces and materials, plus an optional preview camera.
#[derive(Clone, Debug)]
pub struct Scene {
    /// Name: the built-in name, or the file stem.
    pub name: String,
    /// Where it came from: `builtin:NAME` or the file path.
    pub source: String,
    /// Vertex positions (f64: geometry stays exact as loaded; f32 only at the Embree
    /// boundary and in the output files).
    pub positions: Vec<DVec3>,
    /// Planar convex polygons.
    pub faces: Vec<Face>,
    /// Texture coordinates (OBJ `vt`, `u` right and `v` up), indexed by [`Face::uv`].
    pub uvs: Vec<DVec2>,
    /// Materials referenced by the faces.
    pub materials: Vec<Material>,
    /// Object names, each used by some face and none repeated: the OBJ `o` / `g` names,
    /// or the scene's name for faces before any such statement.
    pub objects: Vec<String>,
    /// Length unit of the coordinates (from a `#@units` line), if the scene says.
    pub units: Option<Units>,
    /// Preview camera (from a `#@camera` line), if the scene carries one.
    pub camera: Option<Camera>,
    /// Things the loader repaired or dropped (degenerate faces...), for the summary.
    pub warnings: Vec<String>,
}

impl Scene {
    /// Axis-aligned bounds of the positions used by faces.
    pub fn bounds(&self) -> (DVec3, DVec3) {
        let mut lo = DVec3::splat(f64::INFINITY);
        let mut hi = DVec3::splat(f64::NEG_INFINITY);
        for f in &self.faces {
            for &c in f.corner_slice() {
                let p = self.positions[c as usize];
                lo = lo.min(p);
                hi = hi.max(p);
            }
        }
        (lo, hi)
    }

    /// The preview camera: the scene's own, or one framing its bounds.
    pub fn camera_or_framing(&self) -> Camera {
        self.camera.unwrap_or_else(|| {
            self.interior_camera().unwrap_or_else(|| {
                let (lo, hi) = self.bounds();
                Camera::framing(lo.as_vec3(), hi.as_vec3())
            })
        })
    }

    /// For a closed room, a camera inside it: when every one of 26 rays from the centre of
    /// the bounds (along the axes, the face diagonals and the body diagonals) first meets
    /// the front of a face, the scene is taken to be seen from inside, and a camera from
    /// outside would show only the backs of its walls. The eye is then 90% of the way
    /// from the centre toward the wall at the negative end of the longer horizontal axis
    /// (x or z; +y up), looking across the room, with a 70° field of view. `None` for an
    /// open scene.
    pub fn interior_camera(&self) -> Option<Camera> {
        let (lo, hi) = self.bounds();
        if !(lo.is_finite() && hi.is_finite()) {
            return None;
        }
        let c = (lo + hi) * 0.5;
        let mut dirs = Vec::with_capacity(26);
        for x in -1..=1 {
            for y in -1..=1 {
                for z in -1..=1 {
                    if (x, y, z) != (0, 0, 0) {
                        // Tilted off the exact diagonals, which meet a box's edges and
                        // corners, where a ray can slip between two faces.
                        let d = DVec3::new(x as f64, y as f64, z as f64) + TILT;
                        dirs.push(d.normalize());
                    }
                }
            }
        }
        let mut reach = Vec::with_capacity(dirs.len());
        for d in &dirs {
            let (t, front) = self.first_hit(c, *d)?;
            if !front {
                return None;
            }
            reach.push(t);
        }
        let ext = hi - lo;
        let (axis, k) = if ext.x >= ext.z {
            (DVec3::X, 4) // direction about (-1, 0, 0)
        } else {
            (DVec3::Z, 12) // direction about (0, 0, -1)
        };
        let eye = c - axis * (0.9 * reach[k]);
        Some(Camera {
            eye: eye.as_vec3(),
            target: (c + axis * (0.5 * reach[k])).as_vec3(),
            up: Vec3::Y,
            vfov_deg: 70.0,
        })
    }

    /// The nearest face met by the ray `o + t d` (t > 0): its distance, and whether the ray
    /// meets the face's front (the side its counter-clockwise winding faces). `None` when
    /// the ray leaves the scene.
    fn first_hit(&self, o: DVec3, d: DVec3) -> Option<(f64, bool)> {
        self.extreme_hit(o, d, |t, best| t < best)
    }

    /// The farthest face met by the ray `o + t d` (t > 0), as [`Scene::first_hit`] gives
    /// the nearest: its distance and whether the ray meets its front.
    fn last_hit(&self, o: DVec3, d: DVec3) -> Option<(f64, bool)> {
        self.extreme_hit(o, d, |t, best| t > best)
    }

    /// The hit of the ray `o + t d` (t > 0) that `better(t, best)` prefers over all
    /// others, with whether the ray meets the face's front. Möller and Trumbore's
    /// ray-triangle test over each face's fan (faces are planar and convex).
    fn extreme_hit(
        &self,
        o: DVec3,
        d: DVec3,
        better: impl Fn(f64, f64) -> bool,
    ) -> Option<(f64, bool)> {
        let mut best: Option<(f64, bool)> = None;
        for f in &self.faces {
            let c = f.corner_slice();
            let p = |k: usize| self.positions[c[k] as usize];
            for k in 1..c.len() - 1 {
                let (a, b, e) = (p(0), p(k), p(k + 1));
                let (e1, e2) = (b - a, e - a);
                let h = d.cross(e2);
                let det = e1.dot(h);
                if det.abs() < 1e-300 {
                    continue;
                }
                let s = o - a;
                let u = s.dot(h) / det;
                let q = s.cross(e1);
                let v = d.dot(q) / det;
                let t = e2.dot(q) / det;
                if u < 0.0 || v < 0.0 || u + v > 1.0 || t <= 0.0 {
                    continue;
                }
                if best.is_none_or(|(bt, _)| better(t, bt)) {
                    // det = -d . (e1 x e2): positive when the face's normal faces the
                    // ray's origin. A two-sided face has a front toward every ray (its
                    // twin lies on it, wound the other way).
                    best = Some((t, det > 0.0 || f.is_two_sided()));
                }
            }
        }
        best
    }

    /// A warning, before any work, when the scene looks like a closed room modelled with
    /// its normals pointing out (Blender's default cube scaled up): every one of the 26
    /// probe rays of [`Scene::interior_camera`] from the centre of the bounds meets some
    /// face (the scene is closed around that point), and the outermost face met, the
    /// room's shell, shows its back to at least half of them. Surfaces emit and receive
    /// only on their front, so such a room sees nothing from inside. `None` otherwise
    /// (an open scene, a room wound inward, a two-sided shell, an object seen from
    /// outside with the room around it).
    pub fn inside_out_warning(&self) -> Option<String> {
        let (lo, hi) = self.bounds();
        if !(lo.is_finite() && hi.is_finite()) {
            return None;
        }
        let c = (lo + hi) * 0.5;
        let mut backs = 0;
        let mut probes = 0;
        for x in -1..=1 {
            for y in -1..=1 {
                for z in -1..=1 {
                    if (x, y, z) == (0, 0, 0) {
                        continue;
                    }
                    let d = (DVec3::new(x as f64, y as f64, z as f64) + TILT).normalize();
                    let (_, front) = self.last_hit(c, d)?;
                    probes += 1;
                    if !front {
                        backs += 1;
                    }
                }
            }
        }
        (2 * backs >= probes).then(|| {
            format!(
                "`{}` looks like a closed room whose faces point out of it: {backs} of \
                 {probes} rays from the centre of its bounds leave through the back of its \
                 outermost faces. Faces emit and receive only on the side their \
                 counter-clockwise winding faces, so from inside nothing is seen: bake with \
                 --two-sided (every face both ways; or `#@two-sided` in a material of the \
                 MTL), or flip the normals (Blender: Mesh > Normals > Flip, then export \
                 again)",
                self.name
            )
        })
    }

    /// Makes faces two-sided: every face whose material is two-sided (MTL `#@two-sided`),
    /// or every face when `all`, gets a twin appended to [`Scene::faces`]: the same
    /// corners and texture coordinates wound the other way (corner 0 first), the same
    /// material, object and line, marked [`Face::back`]. The two sides are separate
    /// surfaces: each emits its material's `Ke`, reflects its `Kd` and receives only on
    /// its own side, so form factors, solvers and outputs need nothing else. Faces that
    /// already have a twin are left alone (calling this twice changes nothing). Returns
    /// the number of twins added.
    pub fn make_two_sided(&mut self, all: bool) -> usize {
        let n = self.faces.len();
        let mut added = 0;
        for k in 0..n {
            let f = self.faces[k];
            if f.is_two_sided() || !(all || self.materials[f.material as usize].two_sided) {
                continue;
            }
            let rev = |a: [u32; 4]| {
                if f.len() == 3 {
                    [a[0], a[2], a[1], Face::NONE]
                } else {
                    [a[0], a[3], a[2], a[1]]
                }
            };
            let twin = self.faces.len() as u32;
            self.faces.push(Face {
                corners: rev(f.corners),
                uv: rev(f.uv),
                twin: k as u32,
                back: true,
                ..f
            });
            self.faces[k].twin = twin;
            added += 1;
        }
        added
    }

    /// Errors unless some face has an emitting material.
    pub fn require_emitter(&self) -> Result<()> {
        let lit = self
            .faces
            .iter()
            .any(|f| self.materials[f.material as usize].is_emitter());
        if lit {
            Ok(())
        } else {
            Err(Error::Scene {
                scene: self.source.clone(),
                msg: "no emitter: no face has a material with Ke > 0, so every radiosity \
                      would be 0"
                    .into(),
            })
        }
    }

    /// Index of the material named `name`.
    pub fn material_index(&self, name: &str) -> Option<usize> {
        self.materials.iter().position(|m| m.name == name)
    }

    /// Sets reflectance and emission of the material named `name`, checking the ranges.
    pub fn set_material(&mut self, name: &str, rho: [f64; 3], emit: [f64; 3]) -> Result<()> {
        let k = self.material_index(name).ok_or_else(|| Error::Scene {
            scene: self.source.clone(),
            msg: format!("no material named `{name}`"),
        })?;
        let m = Material {
            name: name.to_string(),
            rho,
            emit,
            thermal: self.materials[k].thermal,
            two_sided: self.materials[k].two_sided,
        };
        m.validate().map_err(|msg| Error::Material {
            path: self.source.clone().into(),
            line: None,
            material: name.to_string(),
            msg,
        })?;
        self.materials[k] = m;
        Ok(())
    }

    /// Loads a scene by built-in name or by path to an OBJ file, as written (the
    /// pipeline's `load_scene` then makes faces two-sided as asked and raises faces lying
    /// on others, [`Scene::raise_coincident`]).
    pub fn load(name_or_path: &str) -> Result<Scene> {
        if let Some(scene) = builtin::load(name_or_path)? {
            return Ok(scene);
        }
        if let Some(scene) = generated::load(name_or_path)? {
            return Ok(scene);
        }
        let path = std::path::Path::new(name_or_path);
        if path.exists() || name_or_path.contains('/') || name_or_path.ends_with(".obj") {
            return obj::load_file(path);
        }
        Err(Error::UnknownScene {
            name: name_or_path.to_string(),
            known: format!("{}, room-spheres-N, city-N", builtin::NAMES.join(", ")),
        })
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    /// A 4 x 3 x 2 box (x, y, z) with its six faces wound inward or outward.
    fn boxed(inward: bool) -> super::Scene {
        let faces = if inward {
            "f 2 3 4 1\nf 8 7 6 5\nf 5 6 2 1\nf 3 7 8 4\nf 4 8 5 1\nf 6 7 3 2\n"
        } else {
            "f 1 4 3 2\nf 5 6 7 8\nf 1 2 6 5\nf 4 8 7 3\nf 1 5 8 4\nf 2 3 7 6\n"
        };
        let obj = format!(
            "v 0 0 0\nv 4 0 0\nv 4 3 0\nv 0 3 0\nv 0 0 2\nv 4 0 2\nv 4 3 2\nv 0 3 2\n{faces}"
        );
        super::obj::parse("box", Path::new("box.obj"), &obj, &|_| unreachable!()).unwrap()
    }

    #[test]
    fn a_closed_room_is_previewed_from_inside_and_an_open_scene_from_outside() {
        let room = boxed(true);
        let cam = room.interior_camera().expect("a closed room");
        // Inside, 90% of the way toward the x = 0 wall (x is the longer horizontal axis),
        // looking along +x.
        assert!(
            (cam.eye - glam::Vec3::new(0.2, 1.5, 1.0)).length() < 0.05,
            "{cam:?}"
        );
        assert!(cam.target.x > cam.eye.x && cam.vfov_deg == 70.0);
        assert_eq!(room.camera_or_framing(), cam);
        // Wound outward, the same box is seen from outside.
        let shell = boxed(false);
        assert!(shell.interior_camera().is_none());
        let outside = shell.camera_or_framing();
        let (lo, hi) = shell.bounds();
        let e = outside.eye.as_dvec3();
        assert!(e.cmplt(lo).any() || e.cmpgt(hi).any(), "{outside:?}");
        // A box with one wall missing is open.
        let mut open = boxed(true);
        open.faces.pop();
        assert!(open.interior_camera().is_none());
        // A scene's own camera wins.
        for name in ["cornell", "cube"] {
            let s = super::Scene::load(name).unwrap();
            assert_eq!(s.camera_or_framing(), s.camera.unwrap(), "{name}");
        }
    }
}
