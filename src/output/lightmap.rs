//! Lightmaps: the baked radiosity as textures in the OBJ's own texture coordinates.
//!
//! `radiosity bake SCENE --lightmap RES` writes, for each object of the scene (its `o` or
//! `g` name) and each side that has faces, one OpenEXR texture of `RES x RES` texels in
//! the object's `vt` space, so a renderer or game engine can put the bake back onto the
//! user's own model through the UV map it already has:
//!
//! - one texture per object, not one atlas: objects exported from Blender (or most modelling
//!   tools) each have UVs filling the unit square on their own, overlapping one another's;
//!   an atlas would need new UVs, and the point is to keep the model's;
//! - `lightmap-NAME.exr` holds the front of the faces (the side the OBJ winds them toward),
//!   `lightmap-NAME-back.exr` the back of two-sided faces (`--two-sided`, `#@two-sided`):
//!   both sides share one UV chart but see different light (a wall of a room modelled with
//!   its normals out is lit on its back). A renderer picks the texture by the side it sees
//!   (Blender: *Geometry > Backfacing*);
//! - channels `R`, `G`, `B`: the linear radiosity (the units of the scene's `Ke`), not
//!   multiplied by the alpha; `A`: coverage, 1 where the texel's centre lies on a face of
//!   the object, 0 elsewhere (a renderer should not treat it as opacity);
//! - header attributes `radiosity:layout` ([`LAYOUT`]), `radiosity:object`,
//!   `radiosity:side` (`front` or `back`), `radiosity:scene`;
//! - texel `(x, y)` (x to the right, y down, row 0 on top) has its centre at
//!   `u = (x + 0.5) / RES`, `v = 1 - (y + 0.5) / RES`: `v` up, as OBJ and Blender have it.
//!
//! The value of a covered texel is the radiosity at its surface point, interpolated from
//! the solved mesh exactly as the other outputs show it: each output triangle (a patch
//! triangle, [`crate::output::interpolate`]) is drawn in UV space with its three vertex
//! values, and the texel takes the linear (barycentric) interpolation at its centre, which
//! is the Gouraud shading of `mesh.ply` and the preview at that point. A triangle's corner
//! UVs come from its face: patches subdivide the scene's faces (a quad bilinearly, a
//! triangle into similar triangles, [`crate::mesh`]), so a corner's point is mapped back
//! to its face's parameters (barycentric on a triangle, the inverse of the bilinear map on a
//! quad, in the face's plane) and the face's corner UVs interpolated there; polygons of
//! more corners were cut into triangles whose added points carry UVs interpolated from
//! the polygon's ([`crate::scene::polygon::Meshed::corner_weights`]).
//!
//! Texels a triangle only partly covers take no value from it (their centre is outside);
//! they and a margin of [`MARGIN`] texels around every chart are filled by dilation: each
//! pass gives every empty texel next to filled ones the mean of its filled neighbours
//! (8-neighbourhood), so bilinear filtering and the first mip levels read the chart's own
//! values across its seams instead of black. Texels claimed by two triangles' interiors
//! (overlapping UV charts) hold their mean and are counted, and a warning says so.
//!
//! Every face of the scene must have texture coordinates: [`check`] refuses the run
//! before any work otherwise, naming the file, the line, the face's object and how many
//! faces lack them. `lightmaps.json` lists the files with their object, side, faces and
//! texel counts, and the preview's exposure (for a viewer that wants the same picture).

use std::collections::HashMap;
use std::path::Path;

use glam::{DVec2, DVec3};
use serde::Serialize;

use super::vertex::VertexRadiosity;
use crate::error::{Error, Result};
use crate::mesh::PatchSet;
use crate::scene::{Face, Scene};

/// Smallest and largest lightmap side, in texels.
pub const RES_RANGE: std::ops::RangeInclusive<usize> = 8..=8192;

/// Texels of dilation around every chart.
pub const MARGIN: usize = 4;

/// The `radiosity:layout` attribute of the lightmaps.
pub const LAYOUT: &str = "radiosity-lightmap/1 (texel (x, y) at u = (x + 0.5) / width, \
                          v = 1 - (y + 0.5) / height; R G B linear radiosity, A coverage)";

/// Name of the index of the lightmaps in the bake folder.
pub const INDEX: &str = "lightmaps.json";

/// Checks, before any work, that `scene` can be lightmapped at `res` texels a side: the
/// size is in [`RES_RANGE`] and every face has texture coordinates. Returns warnings: faces
/// whose texture coordinates leave the unit square (the texture covers only it).
pub fn check(scene: &Scene, res: usize) -> Result<Vec<String>> {
    if !RES_RANGE.contains(&res) {
        return Err(Error::Config(format!(
            "--lightmap {res}: the lightmap side must be between {} and {} texels",
            RES_RANGE.start(),
            RES_RANGE.end()
        )));
    }
    let missing: Vec<&Face> = scene.faces.iter().filter(|f| !f.has_uv()).collect();
    if let Some(f) = missing.first() {
        let object = &scene.objects[f.object as usize];
        let of_object = missing.iter().filter(|g| g.object == f.object).count();
        let at = if f.line > 0 {
            format!("{}:{}", scene.source, f.line)
        } else {
            scene.source.clone()
        };
        return Err(Error::Scene {
            scene: scene.source.clone(),
            msg: format!(
                "--lightmap needs texture coordinates (`vt`) on every face; {at}: a face \
                 of object `{object}` has none ({of_object} faces of `{object}` and {} in all \
                 lack them): give the model a UV map (Blender: UV > Smart UV Project or \
                 Lightmap Pack) and export it with UV coordinates",
                missing.len()
            ),
        });
    }
    let mut outside: HashMap<u32, (usize, u32)> = HashMap::new();
    for f in scene.faces.iter().filter(|f| !f.back) {
        let off = f.uv[..f.len()].iter().any(|&k| {
            let t = scene.uvs[k as usize];
            !(t.cmpge(DVec2::splat(-1e-6)).all() && t.cmple(DVec2::splat(1.0 + 1e-6)).all())
        });
        if off {
            let e = outside.entry(f.object).or_insert((0, f.line));
            e.0 += 1;
        }
    }
    let mut warnings: Vec<(u32, String)> = outside
        .into_iter()
        .map(|(o, (n, line))| {
            (
                o,
                format!(
                    "{}:{line}: {n} faces of object `{}` have texture coordinates outside \
                     [0, 1]: the lightmap covers the unit square only, and what lies \
                     outside it is not baked",
                    scene.source, scene.objects[o as usize]
                ),
            )
        })
        .collect();
    warnings.sort();
    Ok(warnings.into_iter().map(|(_, w)| w).collect())
}

/// One lightmap: an object's side, drawn and dilated.
#[derive(Clone, Debug, PartialEq)]
pub struct Lightmap {
    /// Object index ([`Scene::objects`]).
    pub object: u32,
    /// True for the back of two-sided faces.
    pub back: bool,
    /// Texels a side.
    pub size: usize,
    /// `R G B A` per texel, row-major, row 0 on top.
    pub rgba: Vec<[f32; 4]>,
    /// Faces drawn.
    pub faces: usize,
    /// Texels whose centre lies on a face.
    pub covered: usize,
    /// Texels claimed by the interiors of two triangles or more (overlapping UVs).
    pub overlapping: usize,
}

/// Texture coordinates of the point `x` of face `f`: its face parameters mapped through
/// the corners' UVs (see the module docs).
pub fn face_uv(scene: &Scene, f: &Face, x: DVec3) -> DVec2 {
    let p: Vec<DVec3> = f
        .corner_slice()
        .iter()
        .map(|&c| scene.positions[c as usize])
        .collect();
    let t: Vec<DVec2> = f.uv[..f.len()]
        .iter()
        .map(|&k| scene.uvs[k as usize])
        .collect();
    if p.len() == 3 {
        let [a, b, c] = barycentric(p[0], p[1], p[2], x);
        t[0] * a + t[1] * b + t[2] * c
    } else {
        let (s, r) = quad_parameters(&p, x);
        t[0] * ((1.0 - s) * (1.0 - r))
            + t[1] * (s * (1.0 - r))
            + t[2] * (s * r)
            + t[3] * ((1.0 - s) * r)
    }
}

/// Barycentric coordinates of `x` (projected onto the triangle's plane) in `a, b, c`.
fn barycentric(a: DVec3, b: DVec3, c: DVec3, x: DVec3) -> [f64; 3] {
    let (e1, e2, d) = (b - a, c - a, x - a);
    let (d11, d12, d22) = (e1.dot(e1), e1.dot(e2), e2.dot(e2));
    let (b1, b2) = (d.dot(e1), d.dot(e2));
    let det = d11 * d22 - d12 * d12;
    if det.is_nan() || det <= 0.0 {
        return [1.0, 0.0, 0.0];
    }
    let v = (d22 * b1 - d12 * b2) / det;
    let w = (d11 * b2 - d12 * b1) / det;
    [1.0 - v - w, v, w]
}

/// The parameters `(s, t)`, clamped into the unit square, of the point `x` of the quad `p`
/// under the patch mesher's bilinear map ([`crate::mesh::inverse_bilinear`]), solved in the
/// quad's plane (Newell normal) in units of its longer diagonal.
fn quad_parameters(p: &[DVec3], x: DVec3) -> (f64, f64) {
    let n = crate::scene::polygon::newell(p).normalize_or_zero();
    let a1 = n.any_orthonormal_vector();
    let a2 = n.cross(a1);
    let scale = (p[2] - p[0]).length().max((p[3] - p[1]).length());
    if scale.is_nan() || scale <= 0.0 {
        return (0.0, 0.0);
    }
    let flat = |q: DVec3| DVec2::new((q - p[0]).dot(a1), (q - p[0]).dot(a2)) / scale;
    let (e, f) = (flat(p[1]), flat(p[3]));
    let (s, t) = crate::mesh::inverse_bilinear(e, f, flat(p[2]) - e - f, flat(x));
    let unit = |r: f64| {
        if r.is_finite() {
            r.clamp(0.0, 1.0)
        } else {
            0.0
        }
    };
    (unit(s), unit(t))
}

/// The lightmaps of a bake: for each object and side with faces, in object order (front
/// before back), `res` texels a side, drawn from the output mesh `verts` of `patches`
/// (whose patches subdivide `scene`'s faces) and dilated by [`MARGIN`] texels.
pub fn render(
    scene: &Scene,
    patches: &PatchSet,
    verts: &VertexRadiosity,
    res: usize,
) -> Vec<Lightmap> {
    // Output triangles by (object, side).
    let mut groups: std::collections::BTreeMap<(u32, bool), Vec<usize>> = Default::default();
    for (t, &p) in verts.patch_of_triangle.iter().enumerate() {
        let f = &scene.faces[patches.face[p as usize] as usize];
        groups.entry((f.object, f.back)).or_default().push(t);
    }
    groups
        .into_iter()
        .map(|((object, back), tris)| draw(scene, patches, verts, res, object, back, &tris))
        .collect()
}

/// Draws the output triangles `tris` into one lightmap and dilates it.
fn draw(
    scene: &Scene,
    patches: &PatchSet,
    verts: &VertexRadiosity,
    res: usize,
    object: u32,
    back: bool,
    tris: &[usize],
) -> Lightmap {
    let mut sum = vec![[0.0f64; 3]; res * res];
    let mut hits = vec![0u32; res * res];
    let mut strict = vec![0u8; res * res];
    let mut faces: Vec<u32> = Vec::new();
    let r = res as f64;
    for &t in tris {
        let fi = patches.face[verts.patch_of_triangle[t] as usize];
        faces.push(fi);
        let face = &scene.faces[fi as usize];
        let pv = patches.triangles[t];
        let uv = pv.map(|k| face_uv(scene, face, patches.vertices[k as usize]));
        let rgb = verts.triangles[t].map(|k| verts.rgb[k as usize]);
        // Texel space: x = u res, y = (1 - v) res; texel (i, j) has its centre at + 0.5.
        let q = uv.map(|t| DVec2::new(t.x * r, (1.0 - t.y) * r));
        let area = (q[1] - q[0]).perp_dot(q[2] - q[0]);
        if area.is_nan() || area.abs() <= 1e-12 {
            continue;
        }
        let lo = q[0].min(q[1]).min(q[2]);
        let hi = q[0].max(q[1]).max(q[2]);
        let (x0, x1) = (
            (lo.x - 0.5).ceil().max(0.0) as usize,
            ((hi.x - 0.5).floor().min(r - 1.0)).max(-1.0),
        );
        let (y0, y1) = (
            (lo.y - 0.5).ceil().max(0.0) as usize,
            ((hi.y - 0.5).floor().min(r - 1.0)).max(-1.0),
        );
        if x1 < 0.0 || y1 < 0.0 {
            continue;
        }
        for y in y0..=(y1 as usize) {
            for x in x0..=(x1 as usize) {
                let c = DVec2::new(x as f64 + 0.5, y as f64 + 0.5);
                let l = [
                    (q[2] - q[1]).perp_dot(c - q[1]) / area,
                    (q[0] - q[2]).perp_dot(c - q[2]) / area,
                    (q[1] - q[0]).perp_dot(c - q[0]) / area,
                ];
                if l.iter().any(|&w| w < -1e-12) {
                    continue;
                }
                let k = y * res + x;
                for ch in 0..3 {
                    sum[k][ch] += (0..3).map(|v| l[v] * f64::from(rgb[v][ch])).sum::<f64>();
                }
                hits[k] += 1;
                if l.iter().all(|&w| w > 1e-9) {
                    strict[k] = strict[k].saturating_add(1);
                }
            }
        }
    }
    faces.sort_unstable();
    faces.dedup();
    let mut rgba: Vec<[f32; 4]> = sum
        .iter()
        .zip(&hits)
        .map(|(s, &n)| {
            if n == 0 {
                [0.0; 4]
            } else {
                let m = f64::from(n);
                [(s[0] / m) as f32, (s[1] / m) as f32, (s[2] / m) as f32, 1.0]
            }
        })
        .collect();
    let covered = hits.iter().filter(|&&n| n > 0).count();
    let overlapping = strict.iter().filter(|&&n| n > 1).count();
    let filled: Vec<bool> = hits.iter().map(|&n| n > 0).collect();
    dilate(&mut rgba, filled, res, MARGIN);
    Lightmap {
        object,
        back,
        size: res,
        rgba,
        faces: faces.len(),
        covered,
        overlapping,
    }
}

/// `passes` passes of dilation over the `size x size` image `rgba`: each empty texel
/// (not `filled`) with filled 8-neighbours takes their mean colour (alpha stays 0) and is
/// filled for the next pass.
pub fn dilate(rgba: &mut [[f32; 4]], mut filled: Vec<bool>, size: usize, passes: usize) {
    for _ in 0..passes {
        let mut next = filled.clone();
        let mut changed = false;
        for y in 0..size {
            for x in 0..size {
                let k = y * size + x;
                if filled[k] {
                    continue;
                }
                let (mut acc, mut n) = ([0.0f32; 3], 0u32);
                for dy in -1i64..=1 {
                    for dx in -1i64..=1 {
                        let (xx, yy) = (x as i64 + dx, y as i64 + dy);
                        if (dx, dy) == (0, 0)
                            || xx < 0
                            || yy < 0
                            || xx >= size as i64
                            || yy >= size as i64
                        {
                            continue;
                        }
                        let j = yy as usize * size + xx as usize;
                        if filled[j] {
                            for c in 0..3 {
                                acc[c] += rgba[j][c];
                            }
                            n += 1;
                        }
                    }
                }
                if n > 0 {
                    let m = n as f32;
                    rgba[k] = [acc[0] / m, acc[1] / m, acc[2] / m, 0.0];
                    next[k] = true;
                    changed = true;
                }
            }
        }
        filled = next;
        if !changed {
            break;
        }
    }
}

/// One file of `lightmaps.json`.
#[derive(Clone, Debug, Serialize)]
struct IndexEntry {
    object: String,
    side: &'static str,
    file: String,
    faces: usize,
    texels_covered: usize,
    texels_overlapping: usize,
}

/// `lightmaps.json`.
#[derive(Clone, Debug, Serialize)]
struct Index<'a> {
    layout: &'a str,
    resolution: usize,
    margin: usize,
    exposure: f32,
    lightmaps: Vec<IndexEntry>,
}

/// A file name for the lightmap of `object` (`-back` for the back side): the name's
/// letters, digits, `.`, `_` and `-`, others as `_`, made unique among `used` (case
/// folded) by a number.
fn file_name(object: &str, back: bool, used: &mut Vec<String>) -> String {
    let clean: String = object
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-') {
                c
            } else {
                '_'
            }
        })
        .collect();
    let side = if back { "-back" } else { "" };
    let mut k = 1;
    loop {
        let n = if k == 1 {
            format!("lightmap-{clean}{side}.exr")
        } else {
            format!("lightmap-{clean}-{k}{side}.exr")
        };
        if !used.contains(&n.to_lowercase()) {
            used.push(n.to_lowercase());
            return n;
        }
        k += 1;
    }
}

/// Renders the lightmaps of a bake ([`render`]) and writes each as an EXR file into `dir`
/// (the bake's temporary folder) with `lightmaps.json`; returns the file names and the
/// warnings (overlapping UVs).
pub fn write_all(
    dir: &Path,
    scene: &Scene,
    patches: &PatchSet,
    verts: &VertexRadiosity,
    res: usize,
    exposure: f32,
) -> Result<(Vec<String>, Vec<String>)> {
    let mut used = Vec::new();
    let mut files = Vec::new();
    let mut entries = Vec::new();
    let mut warnings = Vec::new();
    for lm in render(scene, patches, verts, res) {
        let object = &scene.objects[lm.object as usize];
        let name = file_name(object, lm.back, &mut used);
        let side = if lm.back { "back" } else { "front" };
        write(&dir.join(&name), &lm, &scene.name, object)?;
        if lm.overlapping * 200 > lm.covered {
            warnings.push(format!(
                "{name}: {} of the {} covered texels of object `{object}` ({side}) lie \
                 inside two faces or more: its UV charts overlap, and those texels hold \
                 the mean of the faces' radiosity (unwrap without overlaps, e.g. Blender's \
                 Lightmap Pack or Smart UV Project)",
                lm.overlapping, lm.covered
            ));
        }
        entries.push(IndexEntry {
            object: object.clone(),
            side,
            file: name.clone(),
            faces: lm.faces,
            texels_covered: lm.covered,
            texels_overlapping: lm.overlapping,
        });
        files.push(name);
    }
    let index = Index {
        layout: LAYOUT,
        resolution: res,
        margin: MARGIN,
        exposure,
        lightmaps: entries,
    };
    let path = dir.join(INDEX);
    super::write_json(&path, &index)?;
    files.push(INDEX.to_string());
    Ok((files, warnings))
}

/// Writes one lightmap as EXR (layout in the module docs).
pub fn write(path: &Path, lm: &Lightmap, scene: &str, object: &str) -> Result<()> {
    let plane = |c: usize| lm.rgba.iter().map(|t| t[c]).collect::<Vec<f32>>();
    super::exr::write_image(
        path,
        (lm.size, lm.size),
        vec![
            ("R", plane(0)),
            ("G", plane(1)),
            ("B", plane(2)),
            ("A", plane(3)),
        ],
        &[
            ("radiosity:layout", LAYOUT),
            ("radiosity:object", object),
            ("radiosity:side", if lm.back { "back" } else { "front" }),
            ("radiosity:scene", scene),
        ],
    )
}

/// Reads a lightmap written by [`write()`]: its `R G B A` texels, size, object name and side.
pub fn read(path: &Path) -> Result<(Vec<[f32; 4]>, usize, String, bool)> {
    let img = super::exr::read_image(path)?;
    let bad = |msg: String| Error::Parse {
        path: path.to_path_buf(),
        line: None,
        msg,
    };
    let layout = img
        .attrs
        .get("radiosity:layout")
        .cloned()
        .unwrap_or_default();
    if !layout.starts_with("radiosity-lightmap/1") {
        return Err(bad(format!("not a radiosity lightmap (layout `{layout}`)")));
    }
    let (w, h) = img.size;
    if w != h {
        return Err(bad(format!("a lightmap is square, this is {w} x {h}")));
    }
    let ch = |n: &str| {
        img.channels
            .get(n)
            .ok_or_else(|| bad(format!("no channel `{n}`")))
    };
    let (r, g, b, a) = (ch("R")?, ch("G")?, ch("B")?, ch("A")?);
    let rgba = (0..w * h).map(|k| [r[k], g[k], b[k], a[k]]).collect();
    let object = img
        .attrs
        .get("radiosity:object")
        .cloned()
        .unwrap_or_default();
    let back = img.attrs.get("radiosity:side").map(String::as_str) == Some("back");
    Ok((rgba, w, object, back))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quad_parameters_recover_the_parameters_of_a_skew_quad() {
        let p = [
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(3.0, 0.2, 0.0),
            DVec3::new(2.5, 2.0, 0.0),
            DVec3::new(-0.3, 1.4, 0.0),
        ];
        for &(s, t) in &[(0.0, 0.0), (1.0, 1.0), (0.3, 0.7), (0.9, 0.05), (0.5, 0.5)] {
            let x = p[0] * ((1.0 - s) * (1.0 - t))
                + p[1] * (s * (1.0 - t))
                + p[2] * (s * t)
                + p[3] * ((1.0 - s) * t);
            let (a, b) = quad_parameters(&p, x);
            assert!(
                (a - s).abs() < 1e-12 && (b - t).abs() < 1e-12,
                "{s} {t}: {a} {b}"
            );
        }
    }

    #[test]
    fn dilation_fills_a_margin_around_a_chart_and_keeps_alpha_zero() {
        let size = 16;
        let mut rgba = vec![[0.0f32; 4]; size * size];
        let mut filled = vec![false; size * size];
        // A 2 x 2 chart at (7..9, 7..9) of value 3.
        for y in 7..9 {
            for x in 7..9 {
                rgba[y * size + x] = [3.0, 3.0, 3.0, 1.0];
                filled[y * size + x] = true;
            }
        }
        dilate(&mut rgba, filled, size, 2);
        for y in 0..size {
            for x in 0..size {
                let inside = (7..9).contains(&x) && (7..9).contains(&y);
                let ring = (5..11).contains(&x) && (5..11).contains(&y);
                let t = rgba[y * size + x];
                if inside {
                    assert_eq!(t, [3.0, 3.0, 3.0, 1.0]);
                } else if ring {
                    assert_eq!(t, [3.0, 3.0, 3.0, 0.0], "({x}, {y})");
                } else {
                    assert_eq!(t, [0.0; 4], "({x}, {y})");
                }
            }
        }
    }

    #[test]
    fn file_names_are_clean_and_unique() {
        let mut used = Vec::new();
        assert_eq!(file_name("Room", false, &mut used), "lightmap-Room.exr");
        assert_eq!(file_name("Room", true, &mut used), "lightmap-Room-back.exr");
        assert_eq!(
            file_name("wall, north/1", false, &mut used),
            "lightmap-wall__north_1.exr"
        );
        assert_eq!(file_name("room", false, &mut used), "lightmap-room-2.exr");
    }
}
