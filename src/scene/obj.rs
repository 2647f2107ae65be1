//! OBJ + MTL loading through `tobj`, with errors that name the file and line.
//!
//! `tobj` parses the geometry; this module adds what a demanding user needs around it:
//! - a line scan first, so a NaN or missing coordinate, an unknown material or a
//!   malformed face is reported with its line (tobj's own errors carry no line; when tobj
//!   rejects the file, the failing line is found by parsing prefixes);
//! - its own MTL reader (`newmtl`, `Kd` = reflectance rho, `Ke` = emitted exitance E), so
//!   a value out of range is reported with its line;
//! - cleaning: repeated corners removed, degenerate (zero-area) faces dropped with a
//!   warning naming the line; triangles and planar convex quads kept as they are; every
//!   other polygon (concave, more than 4 corners, or non-planar beyond 1% of its size)
//!   meshed as written by [`super::polygon`]: its exact area in well-shaped triangles, a
//!   non-planar one split along its best diagonals with a warning naming the file and line,
//!   one that is not simple (self-intersecting, touching itself) refused with its line.
//!
//! Objects: each face belongs to the object named by the last `o` or `g` statement before
//! it (the two are read alike, as tobj reads them; `g a b` names the object `a b`), or,
//! before any, to an object named after the scene (the file stem). Statements with the
//! same name make one object; objects left without faces (an empty `o Camera` from
//! Blender, or one whose faces were all degenerate) are dropped.
//!
//! A comment line `#@camera eye X Y Z target X Y Z up X Y Z fov DEGREES` sets the
//! preview camera; `#@units mm`, `#@units cm` or `#@units m` says what length unit the
//! coordinates are in (outputs in metres are scaled by it). In the MTL, a comment line `#@thermal emissivity E temperature K` or
//! `#@thermal emissivity E flux W_PER_M2` after a `newmtl` gives that material's gray
//! emissivity and boundary condition for the thermal mode ([`crate::scene::Thermal`]).

use std::collections::HashMap;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use glam::{DVec2, DVec3, Vec3};

use super::polygon::{self, newell};
use super::{Boundary, Camera, Face, Material, Scene, Thermal, Units};
use crate::error::{Error, Result};
use crate::input::{read_text, MAX_TEXT_BYTES};

/// Reflectance given to faces that use no material, with a warning.
const DEFAULT_RHO: f64 = 0.5;

/// Loads an OBJ file; `mtllib` files are looked up next to it.
///
/// Only regular files are read (a FIFO or a device is refused without being opened), up to
/// [`MAX_TEXT_BYTES`]; a byte that is not UTF-8 is refused with its line unless it is in a
/// comment.
pub fn load_file(path: &Path) -> Result<Scene> {
    let text = read_text(path, MAX_TEXT_BYTES)?;
    let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
    let name = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    parse(&name, path, &text, &|lib: &str| {
        let p = dir.join(lib);
        let t = read_text(&p, MAX_TEXT_BYTES)?;
        Ok((p, t))
    })
}

/// What the line scan learns before tobj runs.
struct Scan {
    mtllibs: Vec<(String, usize)>,
    usemtl: Vec<(String, usize)>,
    face_lines: Vec<usize>,
    /// For each face, the `usemtl` line in force (an index into `usemtl`), if any.
    face_usemtl: Vec<Option<usize>>,
    /// Object names in order of first use (`o`, `g`, or the scene's name).
    objects: Vec<String>,
    /// For each face, its object (an index into `objects`).
    face_object: Vec<u32>,
    camera: Option<Camera>,
    /// The `#@units` line's unit, and its line.
    units: Option<(Units, usize)>,
    /// Texture coordinates, from the `vt` lines.
    uvs: Vec<DVec2>,
    /// For each face, its corners' texture coordinates (indices into `uvs`), when every
    /// corner gives one (tobj fills a missing one with the previous corner's).
    face_uv: Vec<Option<Vec<u32>>>,
}

/// Parses OBJ text. `path` names the source in messages; `mtl` resolves a `mtllib` name
/// to its path and text.
pub fn parse(
    name: &str,
    path: &Path,
    text: &str,
    mtl: &dyn Fn(&str) -> Result<(PathBuf, String)>,
) -> Result<Scene> {
    let scan = scan_lines(name, path, text)?;
    let mut materials: Vec<Material> = Vec::new();
    let mut mtl_warnings = Vec::new();
    for (lib, line) in &scan.mtllibs {
        let (mpath, mtext) = mtl(lib).map_err(|e| match e {
            Error::Io { path: p, source } => Error::Parse {
                path: path.to_path_buf(),
                line: Some(*line),
                msg: format!("mtllib {}: {source}", p.display()),
            },
            Error::Parse {
                path: p,
                line: None,
                msg,
            } => Error::Parse {
                path: path.to_path_buf(),
                line: Some(*line),
                msg: format!("mtllib {}: {msg}", p.display()),
            },
            other => other,
        })?;
        let (read, warnings) = parse_mtl_warning(&mpath, &mtext)?;
        mtl_warnings.extend(warnings);
        for m in read {
            if let Some(k) = materials.iter().position(|x| x.name == m.name) {
                materials[k] = m;
            } else {
                materials.push(m);
            }
        }
    }
    // Materials are assigned here from the `usemtl` lines, not by tobj: tobj appends
    // the list its loader returns once per `mtllib` line, so its indices run past ours as
    // soon as a file has two of them.
    let mut usemtl_material = Vec::with_capacity(scan.usemtl.len());
    for (used, line) in &scan.usemtl {
        let k = materials
            .iter()
            .position(|m| &m.name == used)
            .ok_or_else(|| Error::Parse {
                path: path.to_path_buf(),
                line: Some(*line),
                msg: format!("usemtl `{used}`: no such material in the mtllib files"),
            })?;
        usemtl_material.push(k as u32);
    }
    let models = run_tobj(path, text)?;

    let mut scene = Scene {
        name: name.to_string(),
        source: path.display().to_string(),
        positions: Vec::new(),
        faces: Vec::new(),
        uvs: scan.uvs.clone(),
        materials,
        objects: scan.objects.clone(),
        units: scan.units.map(|(u, _)| u),
        camera: scan.camera,
        warnings: mtl_warnings,
    };
    let mut default_material: Option<u32> = None;
    let mut face_no = 0usize;
    for model in &models {
        let mesh = &model.mesh;
        let base = scene.positions.len() as u32;
        scene.positions.extend(
            mesh.positions
                .chunks_exact(3)
                .map(|p| DVec3::new(p[0], p[1], p[2])),
        );
        let mut start = 0usize;
        let n_faces = if mesh.face_arities.is_empty() {
            mesh.indices.len() / 3
        } else {
            mesh.face_arities.len()
        };
        for f in 0..n_faces {
            let arity = if mesh.face_arities.is_empty() {
                3
            } else {
                mesh.face_arities[f] as usize
            };
            let idx: Vec<u32> = mesh.indices[start..start + arity]
                .iter()
                .map(|&i| i + base)
                .collect();
            start += arity;
            let line = scan.face_lines.get(face_no).copied().unwrap_or(0);
            let uv = scan.face_uv.get(face_no).cloned().flatten();
            let used = scan.face_usemtl.get(face_no).copied().flatten();
            let object = scan.face_object.get(face_no).copied().unwrap_or(0);
            face_no += 1;
            let material = match used {
                Some(u) => usemtl_material[u],
                None => *default_material.get_or_insert_with(|| {
                    scene.materials.push(Material {
                        name: "(none)".into(),
                        rho: [DEFAULT_RHO; 3],
                        emit: [0.0; 3],
                        thermal: None,
                        two_sided: false,
                    });
                    scene.warnings.push(format!(
                        "faces without a material get a grey default with rho = {DEFAULT_RHO}"
                    ));
                    (scene.materials.len() - 1) as u32
                }),
            };
            add_polygon(
                &mut scene,
                path,
                &idx,
                uv.as_deref(),
                material,
                object,
                line,
            )?;
        }
    }
    drop_unused_objects(&mut scene);
    scene.make_two_sided(false);
    if scene.faces.is_empty() {
        return Err(Error::Scene {
            scene: scene.source.clone(),
            msg: "no usable faces (an OBJ scene needs `f` lines with non-degenerate polygons)"
                .into(),
        });
    }
    Ok(scene)
}

fn parse_floats(
    path: &Path,
    line: usize,
    what: &str,
    words: &[&str],
    n: usize,
) -> Result<Vec<f64>> {
    if words.len() < n {
        return Err(Error::Parse {
            path: path.to_path_buf(),
            line: Some(line),
            msg: format!("`{what}` needs {n} numbers, found {}", words.len()),
        });
    }
    words[..n]
        .iter()
        .map(|w| match w.parse::<f64>() {
            Ok(x) if x.is_finite() => Ok(x),
            Ok(x) => Err(Error::Parse {
                path: path.to_path_buf(),
                line: Some(line),
                msg: format!("`{what}` has a non-finite value {x}"),
            }),
            Err(_) => Err(Error::Parse {
                path: path.to_path_buf(),
                line: Some(line),
                msg: format!("`{what}`: `{w}` is not a number"),
            }),
        })
        .collect()
}

/// Refuses values that would not survive the conversion to f32 (Embree's vertex buffer,
/// the preview camera and the output files hold f32): `1e39` would become infinite.
fn check_f32(path: &Path, line: usize, what: &str, values: &[f64]) -> Result<()> {
    match values.iter().find(|x| x.abs() > f32::MAX as f64) {
        Some(x) => Err(Error::Parse {
            path: path.to_path_buf(),
            line: Some(line),
            msg: format!(
                "`{what}` value {x:e} is beyond the f32 range (|x| <= {:e}) it is stored in",
                f32::MAX
            ),
        }),
        None => Ok(()),
    }
}

/// Keeps the objects some face uses, in their order, renumbering the faces' indices.
fn drop_unused_objects(scene: &mut Scene) {
    let mut used = vec![false; scene.objects.len()];
    for f in &scene.faces {
        used[f.object as usize] = true;
    }
    let mut new_index = vec![0u32; scene.objects.len()];
    let mut kept = Vec::with_capacity(scene.objects.len());
    for (k, name) in std::mem::take(&mut scene.objects).into_iter().enumerate() {
        if used[k] {
            new_index[k] = kept.len() as u32;
            kept.push(name);
        }
    }
    scene.objects = kept;
    for f in &mut scene.faces {
        f.object = new_index[f.object as usize];
    }
}

/// The index of the object `name` in `objects`, added if new.
fn object_index(objects: &mut Vec<String>, name: &str) -> u32 {
    match objects.iter().position(|o| o == name) {
        Some(k) => k as u32,
        None => {
            objects.push(name.to_string());
            (objects.len() - 1) as u32
        }
    }
}

fn scan_lines(scene_name: &str, path: &Path, text: &str) -> Result<Scan> {
    let mut scan = Scan {
        mtllibs: Vec::new(),
        usemtl: Vec::new(),
        face_lines: Vec::new(),
        face_usemtl: Vec::new(),
        objects: Vec::new(),
        face_object: Vec::new(),
        camera: None,
        units: None,
        uvs: Vec::new(),
        face_uv: Vec::new(),
    };
    let mut object: Option<u32> = None;
    let mut n_vertices = 0usize;
    for (k, raw) in text.lines().enumerate() {
        let line = k + 1;
        let words: Vec<&str> = raw.split_whitespace().collect();
        let Some((&key, rest)) = words.split_first() else {
            continue;
        };
        match key {
            "v" => {
                let v = parse_floats(path, line, "v", rest, 3)?;
                check_f32(path, line, "v", &v)?;
                n_vertices += 1;
            }
            "vt" => {
                // `vt u v [w]` (tobj needs both u and v; w, for 3D textures, is not used).
                let t = parse_floats(path, line, "vt", rest, 2)?;
                check_f32(path, line, "vt", &t)?;
                scan.uvs.push(DVec2::new(t[0], t[1]));
            }
            "f" => {
                if rest.len() < 3 {
                    return Err(Error::Parse {
                        path: path.to_path_buf(),
                        line: Some(line),
                        msg: format!("a face needs at least 3 corners, found {}", rest.len()),
                    });
                }
                for w in rest {
                    let first = w.split('/').next().unwrap_or("");
                    let ok = match first.parse::<i64>() {
                        Ok(i) if i > 0 => (i as usize) <= n_vertices,
                        Ok(i) if i < 0 => (-i as usize) <= n_vertices,
                        _ => false,
                    };
                    if !ok {
                        return Err(Error::Parse {
                            path: path.to_path_buf(),
                            line: Some(line),
                            msg: format!(
                                "face corner `{w}` is not a vertex index in 1..={n_vertices}"
                            ),
                        });
                    }
                }
                let n_uvs = scan.uvs.len();
                let mut uv = Vec::with_capacity(rest.len());
                for w in rest {
                    let Some(t) = w.split('/').nth(1).filter(|t| !t.is_empty()) else {
                        continue;
                    };
                    let k = match t.parse::<i64>() {
                        Ok(i) if i > 0 && (i as usize) <= n_uvs => Some(i as usize - 1),
                        Ok(i) if i < 0 && (-i as usize) <= n_uvs => Some(n_uvs - (-i as usize)),
                        _ => None,
                    };
                    let k = k.ok_or_else(|| Error::Parse {
                        path: path.to_path_buf(),
                        line: Some(line),
                        msg: format!(
                            "face corner `{w}`: `{t}` is not a texture coordinate (`vt`) \
                             index in 1..={n_uvs}"
                        ),
                    })?;
                    uv.push(k as u32);
                }
                scan.face_uv.push((uv.len() == rest.len()).then_some(uv));
                scan.face_lines.push(line);
                scan.face_usemtl.push(scan.usemtl.len().checked_sub(1));
                let o = *object.get_or_insert_with(|| object_index(&mut scan.objects, scene_name));
                scan.face_object.push(o);
            }
            "o" | "g" => {
                let name = rest.join(" ");
                let name = if name.is_empty() { scene_name } else { &name };
                object = Some(object_index(&mut scan.objects, name));
            }
            "#@units" => {
                let units = match rest {
                    [u] => Units::parse(u),
                    _ => None,
                }
                .ok_or_else(|| Error::Parse {
                    path: path.to_path_buf(),
                    line: Some(line),
                    msg: format!(
                        "#@units `{}`: expected `#@units mm`, `#@units cm` or `#@units m`",
                        rest.join(" ")
                    ),
                })?;
                match scan.units {
                    Some((first, at)) if first != units => {
                        return Err(Error::Parse {
                            path: path.to_path_buf(),
                            line: Some(line),
                            msg: format!(
                                "#@units {} contradicts `#@units {}` at line {at}",
                                units.symbol(),
                                first.symbol()
                            ),
                        })
                    }
                    Some(_) => {}
                    None => scan.units = Some((units, line)),
                }
            }
            "mtllib" => {
                for lib in rest {
                    scan.mtllibs.push((lib.to_string(), line));
                }
            }
            "usemtl" => scan.usemtl.push((rest.join(" "), line)),
            "#@camera" => scan.camera = Some(parse_camera(path, line, rest)?),
            _ => {}
        }
    }
    Ok(scan)
}

fn parse_camera(path: &Path, line: usize, words: &[&str]) -> Result<Camera> {
    let bad = |msg: &str| Error::Parse {
        path: path.to_path_buf(),
        line: Some(line),
        msg: format!(
            "#@camera: {msg} (expected `#@camera eye X Y Z target X Y Z up X Y Z fov DEG`)"
        ),
    };
    let mut vals: HashMap<&str, Vec<f64>> = HashMap::new();
    let mut i = 0;
    while i < words.len() {
        let key = words[i];
        let n = if key == "fov" { 1 } else { 3 };
        if !["eye", "target", "up", "fov"].contains(&key) {
            return Err(bad(&format!("unknown key `{key}`")));
        }
        let v = parse_floats(path, line, key, &words[(i + 1).min(words.len())..], n)?;
        check_f32(path, line, key, &v)?;
        vals.insert(key, v);
        i += 1 + n;
    }
    let v3 = |k: &str| -> Result<Vec3> {
        let v = vals.get(k).ok_or_else(|| bad(&format!("missing `{k}`")))?;
        Ok(Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32))
    };
    let fov = vals.get("fov").map(|v| v[0] as f32).unwrap_or(40.0);
    if !(1.0..179.0).contains(&fov) {
        return Err(bad("fov must be between 1 and 179 degrees"));
    }
    Ok(Camera {
        eye: v3("eye")?,
        target: v3("target")?,
        up: v3("up").unwrap_or(Vec3::Y),
        vfov_deg: fov,
    })
}

/// Parses the words after `#@thermal`: `emissivity E` and exactly one of
/// `temperature K` or `flux W_PER_M2`, in any order.
pub fn parse_thermal(path: &Path, line: usize, words: &[&str]) -> Result<Thermal> {
    let bad = |msg: String| Error::Parse {
        path: path.to_path_buf(),
        line: Some(line),
        msg: format!(
            "#@thermal: {msg} (expected `#@thermal emissivity E temperature K` or \
             `#@thermal emissivity E flux W_PER_M2`)"
        ),
    };
    let (mut eps, mut temperature, mut flux) = (None, None, None);
    let mut k = 0;
    while k < words.len() {
        let key = words[k];
        let slot = match key {
            "emissivity" => &mut eps,
            "temperature" => &mut temperature,
            "flux" => &mut flux,
            _ => return Err(bad(format!("unknown key `{key}`"))),
        };
        if slot.is_some() {
            return Err(bad(format!("`{key}` given twice")));
        }
        let v = parse_floats(path, line, key, &words[(k + 1).min(words.len())..], 1)?;
        *slot = Some(v[0]);
        k += 2;
    }
    let emissivity = eps.ok_or_else(|| bad("missing `emissivity`".into()))?;
    let boundary = match (temperature, flux) {
        (Some(t), None) => Boundary::Temperature(t),
        (None, Some(q)) => Boundary::Flux(q),
        (Some(_), Some(_)) => return Err(bad("give a temperature or a flux, not both".into())),
        (None, None) => return Err(bad("missing `temperature` or `flux`".into())),
    };
    Ok(Thermal {
        emissivity,
        boundary,
    })
}

/// Reads `newmtl`, `Kd` and `Ke` from MTL text, checking ranges with line numbers, and the
/// thermal extension `#@thermal emissivity E temperature K | flux W_PER_M2` (a comment to
/// every other MTL reader; see [`parse_thermal`]).
pub fn parse_mtl(path: &Path, text: &str) -> Result<Vec<Material>> {
    parse_mtl_warning(path, text).map(|(m, _)| m)
}

/// MTL statements that change how a surface looks in a renderer but not its diffuse
/// reflectance or emission, which is all radiosity uses: ignored with a warning.
pub const IGNORED_MTL: [&str; 12] = [
    "map_Kd", "map_Ke", "map_Ka", "map_Ks", "map_Ns", "map_d", "map_Bump", "bump", "norm", "Ks",
    "Tf", "d",
];

/// [`parse_mtl`], with the warnings for what it ignores: a material with no `Kd` (it
/// reflects nothing: black), and the statements of [`IGNORED_MTL`] (once per file and
/// statement, naming the first line), textures above all: a `map_Kd` material is baked
/// with its `Kd` colour alone.
pub fn parse_mtl_warning(path: &Path, text: &str) -> Result<(Vec<Material>, Vec<String>)> {
    let mut warnings = Vec::new();
    let mut has_kd: Vec<bool> = Vec::new();
    let mut ignored: Vec<(&str, usize, usize)> = Vec::new();
    let mut out: Vec<(Material, usize)> = Vec::new();
    for (k, raw) in text.lines().enumerate() {
        let line = k + 1;
        let words: Vec<&str> = raw.split_whitespace().collect();
        let Some((&key, rest)) = words.split_first() else {
            continue;
        };
        let rgb = |what: &str| -> Result<[f64; 3]> {
            let n = if rest.len() == 1 { 1 } else { 3 };
            let v = parse_floats(path, line, what, rest, n)?;
            Ok(if n == 1 {
                [v[0]; 3]
            } else {
                [v[0], v[1], v[2]]
            })
        };
        match key {
            "newmtl" => {
                let name = rest.join(" ");
                if name.is_empty() {
                    return Err(Error::Parse {
                        path: path.to_path_buf(),
                        line: Some(line),
                        msg: "`newmtl` needs a name".into(),
                    });
                }
                out.push((
                    Material {
                        name,
                        rho: [0.0; 3],
                        emit: [0.0; 3],
                        thermal: None,
                        two_sided: false,
                    },
                    line,
                ));
                has_kd.push(false);
            }
            "Kd" | "Ke" => {
                let value = rgb(key)?;
                let Some((m, _)) = out.last_mut() else {
                    return Err(Error::Parse {
                        path: path.to_path_buf(),
                        line: Some(line),
                        msg: format!("`{key}` before any `newmtl`"),
                    });
                };
                if key == "Kd" {
                    m.rho = value;
                    if let Some(k) = has_kd.last_mut() {
                        *k = true;
                    }
                } else {
                    m.emit = value;
                }
                m.validate().map_err(|msg| Error::Material {
                    path: path.to_path_buf(),
                    line: Some(line),
                    material: m.name.clone(),
                    msg,
                })?;
            }
            "#@two-sided" => {
                let Some((m, _)) = out.last_mut() else {
                    return Err(Error::Parse {
                        path: path.to_path_buf(),
                        line: Some(line),
                        msg: "`#@two-sided` before any `newmtl`".into(),
                    });
                };
                if !rest.is_empty() {
                    return Err(Error::Parse {
                        path: path.to_path_buf(),
                        line: Some(line),
                        msg: format!(
                            "`#@two-sided` takes no value, found `{}` (the line alone makes \
                             the material's faces two-sided)",
                            rest.join(" ")
                        ),
                    });
                }
                m.two_sided = true;
            }
            "#@thermal" => {
                let Some((m, _)) = out.last_mut() else {
                    return Err(Error::Parse {
                        path: path.to_path_buf(),
                        line: Some(line),
                        msg: "`#@thermal` before any `newmtl`".into(),
                    });
                };
                let t = parse_thermal(path, line, rest)?;
                t.validate().map_err(|msg| Error::Material {
                    path: path.to_path_buf(),
                    line: Some(line),
                    material: m.name.clone(),
                    msg,
                })?;
                m.thermal = Some(t);
            }
            _ => {
                if let Some(&k) = IGNORED_MTL.iter().find(|&&k| k == key) {
                    match ignored.iter_mut().find(|(x, _, _)| *x == k) {
                        Some((_, _, n)) => *n += 1,
                        None => ignored.push((k, line, 1)),
                    }
                }
            }
        }
    }
    for ((m, line), kd) in out.iter().zip(&has_kd) {
        if !kd && m.emit == [0.0; 3] && m.thermal.is_none() {
            warnings.push(format!(
                "{}:{line}: material `{}` has no `Kd`: it reflects nothing (black)",
                path.display(),
                m.name
            ));
        }
    }
    for (key, line, n) in ignored {
        let what = if key.starts_with("map_") || matches!(key, "bump" | "norm") {
            "textures are not baked; the material's `Kd` colour is used"
        } else {
            "only `Kd` (diffuse reflectance) and `Ke` (emission) shape radiosity"
        };
        let times = if n > 1 {
            format!(" ({n} lines)")
        } else {
            String::new()
        };
        warnings.push(format!(
            "{}:{line}: `{key}` ignored{times}: {what}",
            path.display()
        ));
    }
    Ok((out.into_iter().map(|(m, _)| m).collect(), warnings))
}

/// Runs tobj for the geometry alone (materials come from [`Scan`]); when it fails, finds
/// the first line whose prefix fails, for the message.
fn run_tobj(path: &Path, text: &str) -> Result<Vec<tobj::Model>> {
    let opts = tobj::LoadOptions {
        triangulate: false,
        single_index: false,
        ignore_points: true,
        ignore_lines: true,
    };
    let load = |t: &str| {
        tobj::load_obj_buf(&mut BufReader::new(t.as_bytes()), &opts, |_| {
            Ok((Vec::new(), Default::default()))
        })
    };
    match load(text) {
        Ok((models, _)) => Ok(models),
        Err(e) => {
            let lines: Vec<&str> = text.lines().collect();
            let (mut lo, mut hi) = (0usize, lines.len());
            while lo < hi {
                let mid = (lo + hi) / 2;
                if load(&lines[..=mid].join("\n")).is_err() {
                    hi = mid;
                } else {
                    lo = mid + 1;
                }
            }
            Err(Error::Parse {
                path: path.to_path_buf(),
                line: (lo < lines.len()).then_some(lo + 1),
                msg: format!("malformed OBJ: {e}"),
            })
        }
    }
}

/// Adds a polygon as cleaned faces: repeated corners removed, zero-area polygons dropped
/// with a warning, triangles and planar convex quads kept, anything else meshed by
/// [`polygon::mesh`] (a non-planar one with a warning naming the file and line; one that
/// is not simple refused with an error naming them).
#[allow(clippy::too_many_arguments)]
fn add_polygon(
    scene: &mut Scene,
    path: &Path,
    idx: &[u32],
    uv: Option<&[u32]>,
    material: u32,
    object: u32,
    line: usize,
) -> Result<()> {
    let mut corners: Vec<u32> = Vec::with_capacity(idx.len());
    // Texture coordinates of the kept corners (`Face::NONE` without).
    let mut corner_uv: Vec<u32> = Vec::with_capacity(idx.len());
    for (k, &i) in idx.iter().enumerate() {
        let same = |c: Option<&u32>| {
            c.is_some_and(|&c| c == i || scene.positions[c as usize] == scene.positions[i as usize])
        };
        if !same(corners.last()) {
            corners.push(i);
            corner_uv.push(uv.and_then(|u| u.get(k).copied()).unwrap_or(Face::NONE));
        }
    }
    while corners.len() > 1
        && scene.positions[corners[0] as usize]
            == scene.positions[*corners.last().unwrap_or(&0) as usize]
    {
        corners.pop();
        corner_uv.pop();
    }
    let pts: Vec<DVec3> = corners
        .iter()
        .map(|&i| scene.positions[i as usize])
        .collect();
    let scale = pts
        .iter()
        .flat_map(|a| pts.iter().map(move |b| (*a - *b).length_squared()))
        .fold(0.0, f64::max);
    let n = newell(&pts);
    if corners.len() >= 4 && n.length() <= 1e-10 * scale && !polygon::collinear(&pts) {
        return Err(Error::Parse {
            path: path.to_path_buf(),
            line: Some(line),
            msg: format!(
                "face of {} corners: its signed area is zero but its corners are not on one \
                 line, so its edges cross: it is self-intersecting, not a simple polygon",
                corners.len()
            ),
        });
    }
    if corners.len() < 3 || n.length() <= 1e-10 * scale || scale == 0.0 {
        scene.warnings.push(format!(
            "dropped a degenerate face (zero area) at line {line}"
        ));
        return Ok(());
    }
    let unit = n.normalize();
    // Quads a little out of plane (the published Cornell walls are, by a few mm in 550)
    // stay quads: their sub-patches follow the bilinear surface and are planar to second
    // order. Beyond 1% of the diagonal the quad is split and the user told.
    let planar = pts
        .iter()
        .all(|p| (*p - pts[0]).dot(unit).abs() <= polygon::PLANARITY * scale.sqrt());
    let convex = (0..pts.len()).all(|k| {
        let (a, b, c) = (pts[k], pts[(k + 1) % pts.len()], pts[(k + 2) % pts.len()]);
        (b - a).cross(c - b).dot(unit) > 0.0
    });
    let has_uv = uv.is_some();
    let push = |scene: &mut Scene, c: [u32; 4], t: [u32; 4]| {
        scene.faces.push(Face {
            uv: if has_uv { t } else { [Face::NONE; 4] },
            ..Face::new(c, material, object, line as u32)
        });
    };
    let (c, t) = (&corners, &corner_uv);
    match corners.len() {
        3 => push(
            scene,
            [c[0], c[1], c[2], Face::NONE],
            [t[0], t[1], t[2], Face::NONE],
        ),
        4 if planar && convex => push(scene, [c[0], c[1], c[2], c[3]], [t[0], t[1], t[2], t[3]]),
        len => {
            let meshed = polygon::mesh(&pts).map_err(|msg| Error::Parse {
                path: path.to_path_buf(),
                line: Some(line),
                msg: format!("face of {len} corners: {msg}"),
            })?;
            if let Some(dev) = meshed.non_planar {
                scene.warnings.push(format!(
                    "{}:{line}: split a non-planar face of {len} corners (a corner {:.1}% of \
                     its size from its best-fit plane) along its best diagonals",
                    path.display(),
                    100.0 * dev
                ));
            }
            let base = scene.positions.len() as u32;
            scene.positions.extend_from_slice(&meshed.extra);
            // Texture coordinates of the added points, from the corners' (only when the
            // face has them: the weights of a large polygon's points cost n each).
            let uv_base = scene.uvs.len() as u32;
            if has_uv {
                for k in 0..meshed.extra.len() {
                    let uv = meshed
                        .corner_weights(k)
                        .into_iter()
                        .map(|(c, w)| scene.uvs[corner_uv[c] as usize] * w)
                        .sum();
                    scene.uvs.push(uv);
                }
            }
            let index = |k: usize| {
                if k < len {
                    (corners[k], corner_uv[k])
                } else {
                    (base + (k - len) as u32, uv_base + (k - len) as u32)
                }
            };
            for tri in &meshed.triangles {
                let [a, b, c] = tri.map(index);
                push(
                    scene,
                    [a.0, b.0, c.0, Face::NONE],
                    [a.1, b.1, c.1, Face::NONE],
                );
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn no_mtl(_: &str) -> Result<(PathBuf, String)> {
        Ok((
            PathBuf::from("m.mtl"),
            "newmtl w\nKd 0.5 0.5 0.5\nKe 1 1 1\n".into(),
        ))
    }

    #[test]
    fn quad_and_triangle() {
        let obj =
            "mtllib m.mtl\nusemtl w\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\nf 1 2 3\n";
        let s = parse("t", Path::new("t.obj"), obj, &no_mtl).unwrap();
        assert_eq!(s.faces.len(), 2);
        assert_eq!(s.faces[0].len(), 4);
        assert_eq!(s.faces[1].len(), 3);
        assert_eq!(s.faces[1].line, 8);
        assert!(s.materials[0].is_emitter());
    }

    #[test]
    fn two_mtllib_lines_assign_the_right_materials() {
        // The smallest fuzz case that panicked: the same `mtllib` twice, one `usemtl` face.
        let obj = "mtllib m.mtl\nmtllib m.mtl\nusemtl w\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n";
        let s = parse("t", Path::new("t.obj"), obj, &no_mtl).unwrap();
        assert_eq!(s.materials.len(), 1);
        assert_eq!(s.materials[s.faces[0].material as usize].name, "w");
        // Two libraries, the second redefining a material of the first.
        let libs = |lib: &str| -> Result<(PathBuf, String)> {
            let text = match lib {
                "a.mtl" => "newmtl red\nKd 0.5 0 0\nnewmtl lamp\nKe 1 1 1\n",
                _ => "newmtl blue\nKd 0 0 0.5\nnewmtl red\nKd 0.6 0 0\n",
            };
            Ok((PathBuf::from(lib), text.into()))
        };
        let obj = "mtllib a.mtl\nmtllib b.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\n\
                   usemtl blue\nf 1 2 3\nusemtl lamp\nf 1 2 3\nusemtl red\nf 1 2 3\nf 1 2 3\n";
        let s = parse("t", Path::new("t.obj"), obj, &libs).unwrap();
        let names: Vec<&str> = s
            .faces
            .iter()
            .map(|f| s.materials[f.material as usize].name.as_str())
            .collect();
        assert_eq!(names, ["blue", "lamp", "red", "red"]);
        assert_eq!(s.materials[s.faces[2].material as usize].rho[0], 0.6);
    }

    #[test]
    fn faces_keep_their_object_names() {
        // Faces before any `o` belong to the scene's object; `o` and `g` both name
        // objects; a name used twice is one object; an object without faces (the empty
        // `o Camera`, the degenerate face of `o flat`) is dropped.
        let obj = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\no Camera\no wall, north\n\
                   f 1 2 3\nf 1 3 4\ng lamp\nf 1 2 4\no flat\nf 1 1 2\no wall, north\nf 2 3 4\n";
        let s = parse("room", Path::new("room.obj"), obj, &no_mtl).unwrap();
        assert_eq!(s.objects, ["room", "wall, north", "lamp"]);
        let names: Vec<&str> = s
            .faces
            .iter()
            .map(|f| s.objects[f.object as usize].as_str())
            .collect();
        assert_eq!(
            names,
            ["room", "wall, north", "wall, north", "lamp", "wall, north"]
        );
        assert_eq!(s.units, None);
        // Every patch keeps its face's object.
        let p = crate::mesh::PatchSet::build(&s, crate::mesh::Resolution::Patches(40)).unwrap();
        assert_eq!(p.objects, s.objects);
        for i in 0..p.len() {
            assert_eq!(p.object[i], s.faces[p.face[i] as usize].object);
        }
        assert!(p.object.contains(&2));
    }

    #[test]
    fn units_line_is_read_and_bad_ones_name_their_line() {
        let tri = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n";
        let s = parse(
            "t",
            Path::new("t.obj"),
            &format!("#@units mm\n{tri}"),
            &no_mtl,
        )
        .unwrap();
        assert_eq!(s.units, Some(Units::Millimetres));
        assert_eq!(s.units.unwrap().metres(), 1e-3);
        let same = format!("#@units cm\n{tri}#@units cm\n");
        let s = parse("t", Path::new("t.obj"), &same, &no_mtl).unwrap();
        assert_eq!(s.units, Some(Units::Centimetres));
        for (text, want) in [
            (format!("{tri}#@units inch\n"), "t.obj:5: #@units `inch`"),
            (format!("#@units\n{tri}"), "t.obj:1: #@units ``"),
            (
                format!("#@units m\n{tri}#@units mm\n"),
                "t.obj:6: #@units mm contradicts `#@units m` at line 1",
            ),
        ] {
            let e = parse("t", Path::new("t.obj"), &text, &no_mtl)
                .unwrap_err()
                .to_string();
            assert!(e.contains(want), "{e}");
        }
    }

    #[test]
    fn texture_coordinates_are_kept_and_bad_ones_name_their_line() {
        let obj = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0.5 0 0\n\
                   f 1/1 2/2 3/3 4/-1\nf 1/1 2 3/3\nf 1 2 3\n";
        let s = parse("t", Path::new("t.obj"), obj, &no_mtl).unwrap();
        assert_eq!(s.faces.len(), 3);
        assert!(s.faces[0].has_uv());
        assert_eq!(s.uvs[s.faces[0].uv[3] as usize], DVec2::new(0.5, 0.0));
        // A corner without `vt` (tobj would give it the previous corner's): no UVs.
        assert!(!s.faces[1].has_uv() && !s.faces[2].has_uv());
        for (text, want) in [
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/2 3/1\n",
                "t.obj:5: face corner `2/2`",
            ),
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/-2 2/1 3/1\n",
                "t.obj:5: face corner `1/-2`",
            ),
            (
                "v 0 0 0\nvt nan 0\n",
                "t.obj:2: `vt` has a non-finite value",
            ),
            (
                "v 0 0 0\nvt 0.5\n",
                "t.obj:2: `vt` needs 2 numbers, found 1",
            ),
        ] {
            let e = parse("t", Path::new("t.obj"), text, &no_mtl)
                .unwrap_err()
                .to_string();
            assert!(e.contains(want), "{e}");
        }
        let e = parse_mtl(Path::new("m.mtl"), "#@two-sided\nnewmtl a\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("m.mtl:1") && e.contains("before any `newmtl`"),
            "{e}"
        );
    }

    #[test]
    fn nan_vertex_names_line() {
        let obj = "v 0 0 0\nv nan 0 0\n";
        let e = parse("t", Path::new("t.obj"), obj, &no_mtl)
            .unwrap_err()
            .to_string();
        assert!(e.contains("t.obj:2"), "{e}");
        assert!(e.contains("non-finite"), "{e}");
    }

    #[test]
    fn rho_out_of_range_names_material() {
        let e = parse_mtl(Path::new("m.mtl"), "newmtl x\nKd 1.0 0.2 0.2\n").unwrap_err();
        let e = e.to_string();
        assert!(
            e.contains("m.mtl:2") && e.contains("`x`") && e.contains("[0, 1)"),
            "{e}"
        );
    }

    #[test]
    fn ignored_mtl_statements_and_missing_kd_are_warned_once_with_their_line() {
        let mtl = "newmtl wood\nmap_Kd wood.png\nKd 0.5 0.4 0.3\nnewmtl bare\nd 1\n\
                   newmtl lamp\nKe 10 10 10\nnewmtl tiles\nKd 0.5 0.5 0.5\nmap_Kd t.png\n";
        let (m, w) = parse_mtl_warning(Path::new("m.mtl"), mtl).unwrap();
        assert_eq!(m.len(), 4);
        assert_eq!(w.len(), 3, "{w:?}");
        assert!(w
            .iter()
            .any(|w| w.contains("m.mtl:4") && w.contains("`bare` has no `Kd`")));
        assert!(w.iter().any(|w| w.contains("m.mtl:2")
            && w.contains("`map_Kd` ignored (2 lines)")
            && w.contains("textures are not baked")));
        assert!(w
            .iter()
            .any(|w| w.contains("m.mtl:5") && w.contains("`d` ignored")));
        // The emitter without Kd is not warned about; a material with Kd and Ke neither.
        assert!(!w.iter().any(|w| w.contains("lamp")));
        // Through the OBJ loader, the warnings reach the scene.
        let obj = "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl wood\nf 1 2 3\n";
        let s = parse("t", Path::new("t.obj"), obj, &|_| {
            Ok((PathBuf::from("m.mtl"), mtl.to_string()))
        })
        .unwrap();
        assert_eq!(s.warnings.len(), 3, "{:?}", s.warnings);
    }

    #[test]
    fn nonconvex_quad_is_split() {
        let obj = "v 0 0 0\nv 2 0 0\nv 0.5 0.5 0\nv 0 2 0\nf 1 2 3 4\n";
        let s = parse("t", Path::new("t.obj"), obj, &no_mtl).unwrap();
        assert_eq!(s.faces.len(), 2);
        assert!(s.faces.iter().all(|f| f.len() == 3));
        let area: f64 = s
            .faces
            .iter()
            .map(|f| {
                let p = f.corner_slice().iter().map(|&c| s.positions[c as usize]);
                0.5 * newell(&p.collect::<Vec<_>>()).length()
            })
            .sum();
        assert!((area - 1.0).abs() < 1e-15, "{area}");
    }

    #[test]
    fn polygons_keep_their_area_and_bad_ones_name_their_line() {
        // The L-shaped floor as Blender writes it, from a corner that a fan from corner 1
        // would wrap around the notch (16 m^2 of overlapping triangles instead of 7).
        let obj = "v 4 0 0\nv 4 0 1\nv 1 0 1\nv 1 0 4\nv 0 0 4\nv 0 0 0\nf 1 6 5 4 3 2\n";
        let s = parse("t", Path::new("t.obj"), obj, &no_mtl).unwrap();
        let area: f64 = s
            .faces
            .iter()
            .map(|f| {
                let p: Vec<DVec3> = f
                    .corner_slice()
                    .iter()
                    .map(|&c| s.positions[c as usize])
                    .collect();
                let n = newell(&p);
                assert!(n.y > 0.0, "faces keep the polygon's orientation");
                0.5 * n.length()
            })
            .sum();
        assert_eq!(area, 7.0);
        assert!(s.faces.iter().all(|f| f.line == 7));
        let bad = "v 0 0 0\nv 4 1 0\nv 4 0 0\nv 0 3 0\n\nf 1 2 3 4\n";
        let e = parse("t", Path::new("t.obj"), bad, &no_mtl)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("t.obj:6") && e.contains("self-intersecting"),
            "{e}"
        );
        let lifted = "v 0 0 0\nv 4 0 0\nv 4 1 0.5\nv 0 1 0\nf 1 2 3 4\n";
        let s = parse("t", Path::new("t.obj"), lifted, &no_mtl).unwrap();
        assert_eq!(s.faces.len(), 2);
        assert!(
            s.warnings
                .iter()
                .any(|w| w.contains("t.obj:5") && w.contains("non-planar")),
            "{:?}",
            s.warnings
        );
    }
}
