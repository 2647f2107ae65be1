//! The per-vertex bake as binary glTF 2.0 (`mesh.glb`), for Blender, three.js and game
//! engines: one node and one mesh per scene object, named after it.
//!
//! Layout (glTF 2.0 specification, Khronos, 2021):
//!
//! - one scene, named after the radiosity scene, holding one node per object (with
//!   triangles) in the scene's object order; each node's mesh has one triangle primitive
//!   whose vertices are the bake's output vertices (those of `mesh.ply` and
//!   `radiosity.exr`) used by the object's triangles, renumbered from 0;
//! - attributes, all `FLOAT`: `POSITION` (metres, with its `min` and `max`), `NORMAL`
//!   (unit), `COLOR_0` and the application-specific `_RADIOSITY`; indices are
//!   `UNSIGNED_INT`;
//! - `COLOR_0` is the tone-mapped colour, linear: the radiosity times the preview's
//!   exposure, clamped to [0, 1] as the specification requires of `COLOR_0` (section
//!   3.7.2.1). A viewer that encodes its output to sRGB shows the colours of `mesh.ply` and
//!   `preview.png`;
//! - `_RADIOSITY` is the linear radiosity itself, unclamped, in the solver's units (the
//!   specification reserves names starting with `_` for such attributes);
//! - one material, `KHR_materials_unlit` with a white base colour: the colours are the
//!   light, and a viewer should not light them again (viewers without the extension fall
//!   back to the metallic-roughness material, white times `COLOR_0`);
//! - `asset.extras` records the exposure, the scene's length unit and the scale applied.
//!
//! Units and axes: glTF is in metres with +Y up (section 3.4). Scene coordinates are taken
//! as +Y up, the OBJ convention (Blender exports OBJ with +Y up and imports glTF to its own
//! +Z up), and multiplied by the metres per scene unit ([`crate::scene::Units`]).
//!
//! The JSON is built with `gltf-json` (the gltf-rs project's typed schema of glTF 2.0, the
//! crate family most Rust glTF tools use): field names, enumerations and index types come
//! from the schema rather than from strings typed here, and its validation runs on every
//! file before it is written. The GLB container around it (a 12-byte header, a JSON chunk
//! padded with spaces and a binary chunk padded with zeros to 4 bytes; section 4.4) is
//! written here. The output is checked by the Khronos glTF validator
//! (`scripts/validate-gltf.sh`).

use std::io::Write;
use std::path::Path;

use gltf_json as json;
use json::validation::{Checked::Valid, USize64, Validate};

use super::vertex::VertexRadiosity;
use super::write_atomic;
use crate::error::{Error, Result};

/// What names the objects of a bake's triangles.
#[derive(Clone, Copy, Debug)]
pub struct Objects<'a> {
    /// Object names.
    pub names: &'a [String],
    /// Object (index into `names`) of each triangle of the bake.
    pub of_triangle: &'a [u32],
}

/// How the bake's coordinates and colours are written.
#[derive(Clone, Copy, Debug)]
pub struct GlbSettings<'a> {
    /// Scene name (the glTF scene's name).
    pub scene: &'a str,
    /// Metres per scene unit.
    pub metres_per_unit: f64,
    /// What the unit is, for `asset.extras` (`mm`, or a note that the scene gives none).
    pub units: &'a str,
    /// The preview's exposure: `COLOR_0 = clamp(exposure x radiosity, 0, 1)`.
    pub exposure: f32,
}

/// Writes `v` as `mesh.glb` at `path` (see the [module docs](self)).
pub fn write_glb(
    path: &Path,
    v: &VertexRadiosity,
    objects: Objects,
    settings: &GlbSettings,
) -> Result<()> {
    let bytes = glb_bytes(path, v, objects, settings)?;
    write_atomic(path, |tmp| {
        let mut f = std::fs::File::create(tmp).map_err(|e| Error::io(tmp, e))?;
        f.write_all(&bytes).map_err(|e| Error::io(tmp, e))
    })
}

/// One attribute or index array appended to the binary chunk.
struct Block {
    offset: usize,
    len: usize,
}

fn push_f32(bin: &mut Vec<u8>, values: impl Iterator<Item = f32>) -> Block {
    let offset = bin.len();
    for x in values {
        bin.extend_from_slice(&x.to_le_bytes());
    }
    Block {
        offset,
        len: bin.len() - offset,
    }
}

/// The whole `.glb` file of `v`.
pub fn glb_bytes(
    path: &Path,
    v: &VertexRadiosity,
    objects: Objects,
    settings: &GlbSettings,
) -> Result<Vec<u8>> {
    let n = v.checked_len(path)?;
    let refuse = |msg: String| Error::Output {
        path: path.to_path_buf(),
        msg,
    };
    if objects.of_triangle.len() != v.triangles.len() {
        return Err(refuse(format!(
            "{} object indices for {} triangles",
            objects.of_triangle.len(),
            v.triangles.len()
        )));
    }
    if let Some(&o) = objects
        .of_triangle
        .iter()
        .find(|&&o| o as usize >= objects.names.len())
    {
        return Err(refuse(format!(
            "object {o} of {} named",
            objects.names.len()
        )));
    }
    if let Some(t) = v
        .triangles
        .iter()
        .find(|t| t.iter().any(|&k| k as usize >= n))
    {
        return Err(refuse(format!(
            "triangle {t:?} refers to a vertex beyond the {n} vertices"
        )));
    }
    let scale = settings.metres_per_unit;
    if !(scale.is_finite() && scale > 0.0) {
        return Err(refuse(format!("{scale} metres per unit")));
    }
    let mut root = json::Root {
        asset: json::Asset {
            generator: Some(format!("radiosity {}", env!("CARGO_PKG_VERSION"))),
            extras: Some(
                serde_json::value::to_raw_value(&serde_json::json!({
                    "exposure": settings.exposure,
                    "scene_units": settings.units,
                    "metres_per_scene_unit": scale,
                    "COLOR_0": "linear radiosity x exposure, clamped to [0, 1]",
                    "_RADIOSITY": "linear radiosity, solver units",
                }))
                .map_err(|e| refuse(e.to_string()))?,
            ),
            ..Default::default()
        },
        extensions_used: vec!["KHR_materials_unlit".into()],
        ..Default::default()
    };
    let material = root.push(json::Material {
        name: Some("radiosity (unlit vertex colours)".into()),
        pbr_metallic_roughness: json::material::PbrMetallicRoughness {
            base_color_factor: json::material::PbrBaseColorFactor([1.0; 4]),
            metallic_factor: json::material::StrengthFactor(0.0),
            roughness_factor: json::material::StrengthFactor(1.0),
            ..Default::default()
        },
        extensions: Some(json::extensions::material::Material {
            unlit: Some(json::extensions::material::Unlit {}),
        }),
        ..Default::default()
    });
    let mut bin: Vec<u8> = Vec::new();
    let mut nodes = Vec::new();
    // Triangles of each object, in order.
    let mut tris: Vec<Vec<u32>> = vec![Vec::new(); objects.names.len()];
    for (t, &o) in objects.of_triangle.iter().enumerate() {
        tris[o as usize].push(t as u32);
    }
    let mut local = vec![u32::MAX; n];
    for (o, list) in tris.iter().enumerate() {
        if list.is_empty() {
            continue;
        }
        // The object's vertices in first-use order, and its triangles renumbered.
        let mut used: Vec<u32> = Vec::new();
        let mut indices: Vec<u32> = Vec::with_capacity(list.len() * 3);
        for &t in list {
            for &k in &v.triangles[t as usize] {
                if local[k as usize] == u32::MAX {
                    local[k as usize] = used.len() as u32;
                    used.push(k);
                }
                indices.push(local[k as usize]);
            }
        }
        for &k in &used {
            local[k as usize] = u32::MAX;
        }
        let at = |k: u32| k as usize;
        let pos: Vec<[f32; 3]> = used
            .iter()
            .map(|&k| (v.positions[at(k)].as_dvec3() * scale).as_vec3().to_array())
            .collect();
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for p in &pos {
            for c in 0..3 {
                lo[c] = lo[c].min(p[c]);
                hi[c] = hi[c].max(p[c]);
            }
        }
        if lo.iter().chain(&hi).any(|x| !x.is_finite()) {
            return Err(refuse(format!(
                "object `{}` has a position that is not finite in f32 metres",
                objects.names[o]
            )));
        }
        let b_pos = push_f32(&mut bin, pos.iter().flatten().copied());
        let b_nrm = push_f32(
            &mut bin,
            used.iter().flat_map(|&k| unit(v.normals[at(k)]).to_array()),
        );
        let b_col = push_f32(
            &mut bin,
            used.iter().flat_map(|&k| {
                v.rgb[at(k)].map(|c| {
                    let x = c * settings.exposure;
                    if x.is_nan() {
                        0.0
                    } else {
                        x.clamp(0.0, 1.0)
                    }
                })
            }),
        );
        let b_rad = push_f32(&mut bin, used.iter().flat_map(|&k| v.rgb[at(k)]));
        let b_idx = {
            let offset = bin.len();
            for i in &indices {
                bin.extend_from_slice(&i.to_le_bytes());
            }
            Block {
                offset,
                len: bin.len() - offset,
            }
        };
        let count = used.len() as u64;
        let view = |root: &mut json::Root, b: &Block, target: json::buffer::Target| {
            root.push(json::buffer::View {
                buffer: json::Index::new(0),
                byte_length: USize64(b.len as u64),
                byte_offset: Some(USize64(b.offset as u64)),
                byte_stride: None,
                name: None,
                target: Some(Valid(target)),
                extensions: None,
                extras: None,
            })
        };
        let accessor = |root: &mut json::Root,
                        b: &Block,
                        target: json::buffer::Target,
                        count: u64,
                        component: json::accessor::ComponentType,
                        type_: json::accessor::Type,
                        bounds: Option<([f32; 3], [f32; 3])>| {
            let view = view(root, b, target);
            root.push(json::Accessor {
                buffer_view: Some(view),
                byte_offset: None,
                count: USize64(count),
                component_type: Valid(json::accessor::GenericComponentType(component)),
                extensions: None,
                extras: None,
                type_: Valid(type_),
                min: bounds.map(|(l, _)| serde_json::json!(l)),
                max: bounds.map(|(_, h)| serde_json::json!(h)),
                name: None,
                normalized: false,
                sparse: None,
            })
        };
        use json::accessor::{ComponentType::*, Type::*};
        use json::buffer::Target::*;
        let a_pos = accessor(
            &mut root,
            &b_pos,
            ArrayBuffer,
            count,
            F32,
            Vec3,
            Some((lo, hi)),
        );
        let a_nrm = accessor(&mut root, &b_nrm, ArrayBuffer, count, F32, Vec3, None);
        let a_col = accessor(&mut root, &b_col, ArrayBuffer, count, F32, Vec3, None);
        let a_rad = accessor(&mut root, &b_rad, ArrayBuffer, count, F32, Vec3, None);
        let a_idx = accessor(
            &mut root,
            &b_idx,
            ElementArrayBuffer,
            indices.len() as u64,
            U32,
            Scalar,
            None,
        );
        let mut attributes = std::collections::BTreeMap::new();
        attributes.insert(Valid(json::mesh::Semantic::Positions), a_pos);
        attributes.insert(Valid(json::mesh::Semantic::Normals), a_nrm);
        attributes.insert(Valid(json::mesh::Semantic::Colors(0)), a_col);
        attributes.insert(
            Valid(json::mesh::Semantic::Extras("RADIOSITY".into())),
            a_rad,
        );
        let name = objects.names[o].clone();
        let mesh = root.push(json::Mesh {
            extensions: None,
            extras: None,
            name: Some(name.clone()),
            primitives: vec![json::mesh::Primitive {
                attributes,
                extensions: None,
                extras: None,
                indices: Some(a_idx),
                material: Some(material),
                mode: Valid(json::mesh::Mode::Triangles),
                targets: None,
            }],
            weights: None,
        });
        nodes.push(root.push(json::Node {
            mesh: Some(mesh),
            name: Some(name),
            ..Default::default()
        }));
    }
    if nodes.is_empty() {
        return Err(refuse("no triangles to write".into()));
    }
    root.push(json::Buffer {
        byte_length: USize64(bin.len() as u64),
        name: None,
        uri: None,
        extensions: None,
        extras: None,
    });
    let scene = root.push(json::Scene {
        extensions: None,
        extras: None,
        name: Some(settings.scene.to_string()),
        nodes,
    });
    root.scene = Some(scene);
    let mut problems = Vec::new();
    root.validate(&root, json::Path::new, &mut |p, e| {
        problems.push(format!("{}: {e}", p()))
    });
    if let Some(p) = problems.first() {
        return Err(refuse(format!(
            "invalid glTF ({} problems): {p}",
            problems.len()
        )));
    }
    let text = root.to_vec().map_err(|e| refuse(e.to_string()))?;
    container(&text, &bin).ok_or_else(|| {
        refuse(format!(
            "{} bytes of geometry: beyond the 4 GiB a .glb file can hold",
            bin.len()
        ))
    })
}

/// A unit vector along `n`, or +Y for a zero or non-finite one (a vertex of only buried,
/// zero-area patches), as the glTF `NORMAL` attribute must be unit length.
fn unit(n: glam::Vec3) -> glam::Vec3 {
    let u = n.normalize_or_zero();
    if u == glam::Vec3::ZERO {
        glam::Vec3::Y
    } else {
        u
    }
}

/// The GLB container: header, JSON chunk (space-padded), BIN chunk (zero-padded); `None`
/// when it would pass the 32-bit length of the header.
pub fn container(text: &[u8], bin: &[u8]) -> Option<Vec<u8>> {
    let pad = |k: usize| (4 - k % 4) % 4;
    let json_len = text.len() + pad(text.len());
    let bin_len = bin.len() + pad(bin.len());
    let total = 12 + 8 + json_len + 8 + bin_len;
    let total32 = u32::try_from(total).ok()?;
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&total32.to_le_bytes());
    out.extend_from_slice(&(json_len as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(text);
    out.resize(out.len() + pad(text.len()), b' ');
    out.extend_from_slice(&(bin_len as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(bin);
    out.resize(out.len() + pad(bin.len()), 0);
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    /// Two objects: a unit square (two triangles) and a triangle, sharing vertex 1.
    fn bake() -> VertexRadiosity {
        VertexRadiosity {
            two_sided: Vec::new(),
            positions: vec![
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(1000.0, 0.0, 0.0),
                Vec3::new(1000.0, 0.0, 1000.0),
                Vec3::new(0.0, 0.0, 1000.0),
                Vec3::new(1000.0, 500.0, 0.0),
            ],
            normals: vec![Vec3::Y, Vec3::Y, Vec3::Y, Vec3::Y, Vec3::ZERO],
            rgb: vec![
                [0.5, 1.0, 2.0],
                [0.0, 0.25, 0.5],
                [1.0; 3],
                [1.0; 3],
                [4.0, 0.0, 0.0],
            ],
            triangles: vec![[0, 2, 1], [0, 3, 2], [1, 2, 4]],
            patch_of_triangle: vec![0, 0, 1],
            emits: Vec::new(),
        }
    }

    fn u32_at(b: &[u8], k: usize) -> u32 {
        u32::from_le_bytes(b[k..k + 4].try_into().unwrap())
    }

    fn f32s(b: &[u8], offset: usize, n: usize) -> Vec<f32> {
        (0..n)
            .map(|k| f32::from_le_bytes(b[offset + 4 * k..offset + 4 * k + 4].try_into().unwrap()))
            .collect()
    }

    #[test]
    fn objects_become_named_nodes_in_metres_with_clamped_colours() {
        let names = vec![
            "floor".to_string(),
            "lamp".to_string(),
            "unused".to_string(),
        ];
        let settings = GlbSettings {
            scene: "t",
            metres_per_unit: 1e-3,
            units: "mm",
            exposure: 0.5,
        };
        let objects = Objects {
            names: &names,
            of_triangle: &[0, 0, 1],
        };
        let glb = glb_bytes(Path::new("m.glb"), &bake(), objects, &settings).unwrap();
        assert_eq!(&glb[0..4], b"glTF");
        assert_eq!(u32_at(&glb, 4), 2);
        assert_eq!(u32_at(&glb, 8) as usize, glb.len());
        assert_eq!(glb.len() % 4, 0);
        let json_len = u32_at(&glb, 12) as usize;
        assert_eq!(&glb[16..20], b"JSON");
        let root: serde_json::Value = serde_json::from_slice(&glb[20..20 + json_len]).unwrap();
        let bin_at = 20 + json_len;
        assert_eq!(&glb[bin_at + 4..bin_at + 8], b"BIN\0");
        let bin = &glb[bin_at + 8..];
        // Two nodes (the unused object has no triangles), named, in the scene.
        let node_names: Vec<&str> = root["nodes"]
            .as_array()
            .unwrap()
            .iter()
            .map(|n| n["name"].as_str().unwrap())
            .collect();
        assert_eq!(node_names, ["floor", "lamp"]);
        assert_eq!(root["scenes"][0]["nodes"], serde_json::json!([0, 1]));
        assert_eq!(root["scenes"][0]["name"], "t");
        let prim = &root["meshes"][1]["primitives"][0];
        let attr = |name: &str| prim["attributes"][name].as_u64().unwrap() as usize;
        let acc = &root["accessors"];
        let view = |a: usize| {
            let v = &root["bufferViews"][acc[a]["bufferView"].as_u64().unwrap() as usize];
            v["byteOffset"].as_u64().unwrap() as usize
        };
        // The lamp: vertices 1, 2, 4 renumbered 0, 1, 2; positions in metres.
        let p = attr("POSITION");
        assert_eq!(acc[p]["count"], 3);
        assert_eq!(
            f32s(bin, view(p), 9),
            [1.0, 0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 0.5, 0.0]
        );
        assert_eq!(acc[p]["min"], serde_json::json!([1.0, 0.0, 0.0]));
        assert_eq!(acc[p]["max"], serde_json::json!([1.0, 0.5, 1.0]));
        // COLOR_0: exposure 0.5, clamped; _RADIOSITY: the values as baked.
        let c = attr("COLOR_0");
        assert_eq!(
            f32s(bin, view(c), 9),
            [0.0, 0.125, 0.25, 0.5, 0.5, 0.5, 1.0, 0.0, 0.0]
        );
        let r = attr("_RADIOSITY");
        assert_eq!(f32s(bin, view(r), 9)[6..], [4.0, 0.0, 0.0]);
        // The zero normal became a unit one.
        let nrm = attr("NORMAL");
        assert_eq!(f32s(bin, view(nrm), 9)[6..], [0.0, 1.0, 0.0]);
        let idx = prim["indices"].as_u64().unwrap() as usize;
        let ib = view(idx);
        let ids: Vec<u32> = (0..3).map(|k| u32_at(bin, ib + 4 * k)).collect();
        assert_eq!(ids, [0, 1, 2]);
        assert_eq!(
            root["extensionsUsed"],
            serde_json::json!(["KHR_materials_unlit"])
        );
        assert_eq!(root["asset"]["version"], "2.0");
        assert_eq!(root["asset"]["extras"]["scene_units"], "mm");
    }

    #[test]
    fn inconsistent_bakes_are_refused() {
        let names = vec!["a".to_string()];
        let settings = GlbSettings {
            scene: "t",
            metres_per_unit: 1.0,
            units: "m",
            exposure: 1.0,
        };
        let go = |of: &[u32], v: &VertexRadiosity| {
            glb_bytes(
                Path::new("m.glb"),
                v,
                Objects {
                    names: &names,
                    of_triangle: of,
                },
                &settings,
            )
            .unwrap_err()
            .to_string()
        };
        assert!(go(&[0, 0], &bake()).contains("2 object indices for 3 triangles"));
        assert!(go(&[0, 0, 1], &bake()).contains("object 1 of 1 named"));
        let mut v = bake();
        v.triangles[0][0] = 9;
        assert!(go(&[0, 0, 0], &v).contains("beyond the 5 vertices"));
    }
}
