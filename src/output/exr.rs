//! The per-vertex bake as a self-describing OpenEXR file.
//!
//! ## Layout (version 1)
//!
//! - One pixel per output vertex, in mesh order: vertex `k` is pixel `(k % width, k / width)`
//!   (row-major, rows top to bottom), with `width = min(vertexCount, 4096)` (at least 1) and
//!   `height = ceil(vertexCount / width)`. A bake of up to 4096 vertices is a single row;
//!   larger bakes fill whole rows of 4096 and the unused pixels at the end of the last row
//!   are zero padding, to be ignored (`radiosity:vertexCount` says where the data ends).
//! - One part, scan lines, ZIP compression (lossless), data window at the origin.
//! - Channels, all 32-bit float: `R`, `G`, `B` (linear radiosity, the solver's units),
//!   `P.x`, `P.y`, `P.z` (position, scene units), `N.x`, `N.y`, `N.z` (unit normal).
//!   (The file stores channels sorted by name, as OpenEXR requires.)
//! - Header attributes:
//!   - `radiosity:layout` (string): [`LAYOUT`], starting with `radiosity-vertex-bake/1`;
//!   - `radiosity:vertexCount` (int): the number of vertices;
//!   - `radiosity:scene` (string, UTF-8): the scene name;
//!   - `software` (string): `radiosity` and its version.
//!
//! The triangles are not stored: they are the patch triangles of the scene at the same
//! resolution, and the PLY output carries them for tools that need the mesh.
//!
//! The same layout with other value channels in place of `R G B` and another
//! `radiosity:layout` is written by [`write_vertex_channels`] and read by
//! [`read_vertex_channels`] (the thermal mode's `thermal.exr`).
//!
//! Files are written through [`write_atomic`]. [`read_exr`] reads
//! them back (values are stored as f32, so a round trip is exact).

use std::path::Path;

use exr::prelude::{
    AnyChannel, AnyChannels, AttributeValue, Blocks, Compression, Encoding, FlatSamples, Image,
    Layer, LayerAttributes, LineOrder, ReadChannels, ReadLayers, SmallVec, Text, WritableImage,
};
use glam::Vec3;

use super::vertex::VertexRadiosity;
use super::write_atomic;
use crate::error::{Error, Result};

/// The `radiosity:layout` attribute of files written by this version.
pub const LAYOUT: &str = "radiosity-vertex-bake/1 (pixel k = vertex k, row-major, width = \
                          min(vertexCount, 4096); R G B radiosity, P position, N normal)";

/// The part of [`LAYOUT`] a reader checks: the format name and major version.
pub const LAYOUT_ID: &str = "radiosity-vertex-bake/1";

/// Widest row of the bake; larger bakes wrap onto more rows.
pub const MAX_WIDTH: usize = 4096;

/// Attribute names.
const ATTR_LAYOUT: &str = "radiosity:layout";
const ATTR_COUNT: &str = "radiosity:vertexCount";
const ATTR_SCENE: &str = "radiosity:scene";

/// Channel names of the bake, in the order of the per-vertex values (R G B, P, N).
#[cfg(test)]
const CHANNELS: [&str; 9] = ["R", "G", "B", "P.x", "P.y", "P.z", "N.x", "N.y", "N.z"];

/// The geometry channels every per-vertex file ends with (P, N).
const GEOMETRY: [&str; 6] = ["P.x", "P.y", "P.z", "N.x", "N.y", "N.z"];

/// A bake read back from an EXR file.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ExrBake {
    /// Scene name from the header.
    pub scene: String,
    /// Number of vertices (padding pixels excluded).
    pub vertex_count: usize,
    /// Vertex positions.
    pub positions: Vec<Vec3>,
    /// Vertex normals.
    pub normals: Vec<Vec3>,
    /// Linear radiosity per vertex.
    pub rgb: Vec<[f32; 3]>,
}

/// Image size for `n` vertices: see the module docs.
pub fn layout_size(n: usize) -> (usize, usize) {
    let width = n.clamp(1, MAX_WIDTH);
    (width, n.div_ceil(width).max(1))
}

/// Writes the bake `v` of scene `scene_name` to `path` (layout in the module docs).
pub fn write_exr(path: &Path, v: &VertexRadiosity, scene_name: &str) -> Result<()> {
    v.checked_len(path)?;
    let plane = |c: usize| -> Vec<f32> { v.rgb.iter().map(|x| x[c]).collect() };
    let (r, g, b) = (plane(0), plane(1), plane(2));
    write_vertex_channels(
        path,
        LAYOUT,
        v,
        scene_name,
        &[("R", &r), ("G", &g), ("B", &b)],
    )
}

/// Writes one pixel per vertex of `mesh` (layout in the module docs) with the channels
/// `values` (name, one value per vertex) followed by `P.x P.y P.z N.x N.y N.z`, and the
/// header attribute `radiosity:layout` set to `layout`; `mesh.rgb` is not written. The
/// generic layer under [`write_exr`] and the thermal mode's `thermal.exr`.
pub fn write_vertex_channels(
    path: &Path,
    layout: &str,
    mesh: &VertexRadiosity,
    scene_name: &str,
    values: &[(&str, &[f32])],
) -> Result<()> {
    let n = mesh.checked_len(path)?;
    if let Some((name, v)) = values.iter().find(|(_, v)| v.len() != n) {
        return Err(Error::Output {
            path: path.to_path_buf(),
            msg: format!("channel `{name}` has {} values for {n} vertices", v.len()),
        });
    }
    let count = i32::try_from(n).map_err(|_| Error::Output {
        path: path.to_path_buf(),
        msg: format!("{n} vertices are too many for one EXR bake"),
    })?;
    let (width, height) = layout_size(n);
    let padded = |values: &mut dyn Iterator<Item = f32>| -> Vec<f32> {
        let mut plane = vec![0.0; width * height];
        for (slot, x) in plane.iter_mut().zip(values) {
            *slot = x;
        }
        plane
    };
    let mut planes: Vec<(&str, Vec<f32>)> = values
        .iter()
        .map(|(name, v)| (*name, padded(&mut v.iter().copied())))
        .collect();
    for (k, name) in GEOMETRY.iter().enumerate() {
        let points = if k < 3 {
            &mesh.positions
        } else {
            &mesh.normals
        };
        planes.push((name, padded(&mut points.iter().map(|q| q[k % 3]))));
    }
    let channels: SmallVec<[AnyChannel<FlatSamples>; 4]> = planes
        .into_iter()
        .map(|(name, plane)| AnyChannel::new(name, FlatSamples::F32(plane)))
        .collect();

    let mut attributes = LayerAttributes {
        software_name: Some(text(&format!("radiosity {}", env!("CARGO_PKG_VERSION")))),
        ..LayerAttributes::default()
    };
    attributes
        .other
        .insert(text(ATTR_LAYOUT), AttributeValue::Text(text(layout)));
    attributes
        .other
        .insert(text(ATTR_COUNT), AttributeValue::I32(count));
    attributes
        .other
        .insert(text(ATTR_SCENE), AttributeValue::Text(text(scene_name)));
    write_layer(path, (width, height), attributes, channels)
}

/// Writes one ZIP-compressed scan-line layer to `path` whole or not at all, with its
/// header attributes in name order (the one writer behind every EXR this crate makes).
fn write_layer(
    path: &Path,
    size: (usize, usize),
    attributes: LayerAttributes,
    channels: SmallVec<[AnyChannel<FlatSamples>; 4]>,
) -> Result<()> {
    let encoding = Encoding {
        compression: Compression::ZIP16,
        blocks: Blocks::ScanLines,
        line_order: LineOrder::Increasing,
    };
    let layer = Layer::new(size, attributes, encoding, AnyChannels::sort(channels));
    let mut bytes = Vec::new();
    Image::from_layer(layer)
        .write()
        .to_buffered(std::io::Cursor::new(&mut bytes))
        .map_err(|e| exr_error(path, e, "cannot write the EXR file"))?;
    sort_attributes(&mut bytes).ok_or_else(|| Error::Output {
        path: path.to_path_buf(),
        msg: "the EXR writer made a header this crate cannot read back".into(),
    })?;
    write_atomic(path, |tmp| {
        std::fs::write(tmp, &bytes).map_err(|e| Error::io(tmp, e))
    })
}

/// Puts the header attributes of a single-part EXR file in name order, in place, so that
/// identical bakes are identical files: the exr crate writes custom attributes in the
/// iteration order of a `HashMap`, which changes from run to run. OpenEXR readers accept
/// attributes in any order, and the header keeps its length, so the offset table after it
/// stays valid. `None` when the bytes are not a single-part header this function can walk.
fn sort_attributes(bytes: &mut [u8]) -> Option<()> {
    const MULTIPART: u8 = 0x10; // bit 12 of the version field
    if bytes.get(..4)? != [0x76, 0x2f, 0x31, 0x01] || bytes.get(5)? & MULTIPART != 0 {
        return None;
    }
    let zero = |from: usize| Some(from + bytes.get(from..)?.iter().position(|&b| b == 0)?);
    let (start, mut at) = (8, 8);
    let mut records = Vec::new();
    loop {
        let name_end = zero(at)?;
        if name_end == at {
            break;
        }
        let type_end = zero(name_end + 1)?;
        let size = i32::from_le_bytes(bytes.get(type_end + 1..type_end + 5)?.try_into().ok()?);
        let end = type_end + 5 + usize::try_from(size).ok()?;
        bytes.get(at..end)?;
        records.push((bytes[at..name_end].to_vec(), at..end));
        at = end;
    }
    records.sort_by(|a, b| a.0.cmp(&b.0));
    let sorted: Vec<u8> = records
        .iter()
        .flat_map(|(_, r)| bytes[r.clone()].to_vec())
        .collect();
    bytes[start..at].copy_from_slice(&sorted);
    Some(())
}

/// Reads a bake written by [`write_exr`].
pub fn read_exr(path: &Path) -> Result<ExrBake> {
    let v = read_vertex_channels(path, LAYOUT_ID, &["R", "G", "B"])?;
    let p = &v.values;
    Ok(ExrBake {
        scene: v.scene,
        vertex_count: v.vertex_count,
        rgb: (0..v.vertex_count)
            .map(|k| [p[0][k], p[1][k], p[2][k]])
            .collect(),
        positions: v.positions,
        normals: v.normals,
    })
}

/// A file written by [`write_vertex_channels`], read back.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct VertexChannels {
    /// Scene name from the header.
    pub scene: String,
    /// Number of vertices (padding pixels excluded).
    pub vertex_count: usize,
    /// Vertex positions.
    pub positions: Vec<Vec3>,
    /// Vertex normals.
    pub normals: Vec<Vec3>,
    /// The channels asked for, in the order asked, one value per vertex.
    pub values: Vec<Vec<f32>>,
}

/// Reads a file written by [`write_vertex_channels`] whose `radiosity:layout` starts with
/// `layout_id`: the channels `names` (each required), positions and normals.
pub fn read_vertex_channels(
    path: &Path,
    layout_id: &str,
    names: &[&str],
) -> Result<VertexChannels> {
    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_file(path)
        .map_err(|e| exr_error(path, e, "not a readable EXR file"))?;
    let bad = |msg: String| Error::Parse {
        path: path.to_path_buf(),
        line: None,
        msg,
    };
    let layer = &image.layer_data;
    let attrs = &layer.attributes.other;
    let get_text = |name: &str| match attrs.get(&text(name)) {
        Some(AttributeValue::Text(t)) => Some(String::from_utf8_lossy(t.bytes()).into_owned()),
        _ => None,
    };
    let layout = get_text(ATTR_LAYOUT).ok_or_else(|| {
        bad(format!(
            "no `{ATTR_LAYOUT}` attribute: not a radiosity bake"
        ))
    })?;
    if !layout.starts_with(layout_id) {
        return Err(bad(format!(
            "unsupported bake layout `{layout}` (this version reads `{layout_id}`)"
        )));
    }
    let count = match attrs.get(&text(ATTR_COUNT)) {
        Some(AttributeValue::I32(c)) => usize::try_from(*c).ok(),
        _ => None,
    }
    .ok_or_else(|| bad(format!("missing or negative `{ATTR_COUNT}` attribute")))?;
    let (width, height) = (layer.size.x(), layer.size.y());
    if count > width * height {
        return Err(bad(format!(
            "{count} vertices do not fit in a {width} x {height} image"
        )));
    }
    let scene = get_text(ATTR_SCENE).unwrap_or_default();

    let mut planes: Vec<Vec<f32>> = Vec::with_capacity(names.len() + GEOMETRY.len());
    for &name in names.iter().chain(&GEOMETRY) {
        let channel = layer
            .channel_data
            .list
            .iter()
            .find(|c| c.name == text(name))
            .ok_or_else(|| bad(format!("no channel `{name}`")))?;
        // Pixels are stored row-major, so the first `count` samples are the vertices.
        let plane: Vec<f32> = channel.sample_data.values_as_f32().take(count).collect();
        if plane.len() != count {
            return Err(bad(format!(
                "channel `{name}` holds fewer than {count} samples"
            )));
        }
        planes.push(plane);
    }
    let geometry = planes.split_off(names.len());
    let values = planes;
    let vec3 =
        |k: usize, a: usize| Vec3::new(geometry[a][k], geometry[a + 1][k], geometry[a + 2][k]);
    Ok(VertexChannels {
        scene,
        vertex_count: count,
        positions: (0..count).map(|k| vec3(k, 0)).collect(),
        normals: (0..count).map(|k| vec3(k, 3)).collect(),
        values,
    })
}

/// Writes an image of `width x height` pixels (row-major, rows top to bottom) with the
/// float channels `planes` (name, one value per pixel) and the text attributes `attrs`,
/// ZIP-compressed, attributes in name order (identical images are identical files),
/// through [`write_atomic`]: the lightmaps' writer ([`crate::output::lightmap`]).
pub fn write_image(
    path: &Path,
    (width, height): (usize, usize),
    planes: Vec<(&str, Vec<f32>)>,
    attrs: &[(&str, &str)],
) -> Result<()> {
    if let Some((name, _)) = planes.iter().find(|(_, p)| p.len() != width * height) {
        return Err(Error::Output {
            path: path.to_path_buf(),
            msg: format!("channel `{name}` does not hold {width} x {height} values"),
        });
    }
    let channels: SmallVec<[AnyChannel<FlatSamples>; 4]> = planes
        .into_iter()
        .map(|(name, plane)| AnyChannel::new(name, FlatSamples::F32(plane)))
        .collect();
    let mut attributes = LayerAttributes {
        software_name: Some(text(&format!("radiosity {}", env!("CARGO_PKG_VERSION")))),
        ..LayerAttributes::default()
    };
    for (k, v) in attrs {
        attributes
            .other
            .insert(text(k), AttributeValue::Text(text(v)));
    }
    write_layer(path, (width, height), attributes, channels)
}

/// An image read by [`read_image`]: size, float channels by name, text attributes.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ExrImage {
    /// Width and height in pixels.
    pub size: (usize, usize),
    /// Channels by name, row-major, rows top to bottom.
    pub channels: std::collections::BTreeMap<String, Vec<f32>>,
    /// Text attributes by name.
    pub attrs: std::collections::BTreeMap<String, String>,
}

/// Reads every channel (as f32) and text attribute of the first layer of an EXR file.
pub fn read_image(path: &Path) -> Result<ExrImage> {
    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_file(path)
        .map_err(|e| exr_error(path, e, "not a readable EXR file"))?;
    let layer = &image.layer_data;
    let mut out = ExrImage {
        size: (layer.size.x(), layer.size.y()),
        ..Default::default()
    };
    for c in &layer.channel_data.list {
        out.channels
            .insert(c.name.to_string(), c.sample_data.values_as_f32().collect());
    }
    for (k, v) in &layer.attributes.other {
        if let AttributeValue::Text(t) = v {
            out.attrs.insert(
                k.to_string(),
                String::from_utf8_lossy(t.bytes()).into_owned(),
            );
        }
    }
    Ok(out)
}

/// An EXR text attribute holding the UTF-8 bytes of `s` (NUL bytes dropped, as the format
/// ends strings with them). OpenEXR strings carry no declared encoding; UTF-8 is the
/// common practice.
fn text(s: &str) -> Text {
    let bytes: Vec<u8> = s.bytes().filter(|&b| b != 0).collect();
    Text::from_slice_unchecked(&bytes)
}

/// Maps an `exr` error on `path` to the crate's error.
fn exr_error(path: &Path, e: exr::error::Error, what: &str) -> Error {
    match e {
        exr::error::Error::Io(source) => Error::io(path, source),
        e => Error::Output {
            path: path.to_path_buf(),
            msg: format!("{what}: {e}"),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::test_dir;

    /// A bake of `n` vertices with distinctive, awkward values (negative zero, subnormal,
    /// large, non-round).
    fn bake(n: usize) -> VertexRadiosity {
        let f = |k: usize, c: u32| (k as f32 * 0.37 + c as f32).sin() * 1e3 / (1.0 + k as f32);
        let mut v = VertexRadiosity {
            positions: (0..n)
                .map(|k| Vec3::new(f(k, 0), f(k, 1), f(k, 2)))
                .collect(),
            normals: (0..n)
                .map(|k| Vec3::new(f(k, 3), f(k, 4), f(k, 5)).normalize())
                .collect(),
            rgb: (0..n)
                .map(|k| [f(k, 6).abs(), f(k, 7).abs(), f(k, 8).abs()])
                .collect(),
            ..Default::default()
        };
        if n > 2 {
            v.rgb[0] = [0.0, -0.0, f32::MIN_POSITIVE / 4.0];
            v.positions[1] = Vec3::new(f32::MAX, -1e-30, 123_456.79);
        }
        v
    }

    fn assert_bitwise_equal(v: &VertexRadiosity, back: &ExrBake) {
        assert_eq!(back.vertex_count, v.len());
        let bits3 = |p: Vec3| p.to_array().map(f32::to_bits);
        for k in 0..v.len() {
            assert_eq!(
                bits3(back.positions[k]),
                bits3(v.positions[k]),
                "position {k}"
            );
            assert_eq!(bits3(back.normals[k]), bits3(v.normals[k]), "normal {k}");
            assert_eq!(
                back.rgb[k].map(f32::to_bits),
                v.rgb[k].map(f32::to_bits),
                "rgb {k}"
            );
        }
    }

    #[test]
    fn round_trip_is_bit_exact() {
        let dir = test_dir("exr-round-trip");
        let path = dir.join("bake.exr");
        let v = bake(1000);
        write_exr(&path, &v, "cornell ü").unwrap();
        let back = read_exr(&path).unwrap();
        assert_eq!(back.scene, "cornell ü");
        assert_bitwise_equal(&v, &back);
    }

    #[test]
    fn identical_bakes_are_identical_files() {
        // The attribute map's order changes with every map made; the file must not.
        let dir = test_dir("exr-same-bytes");
        let v = bake(300);
        let files: Vec<Vec<u8>> = (0..8)
            .map(|k| {
                let path = dir.join(format!("bake-{k}.exr"));
                write_exr(&path, &v, "cornell").unwrap();
                assert_bitwise_equal(&v, &read_exr(&path).unwrap());
                std::fs::read(&path).unwrap()
            })
            .collect();
        for (k, f) in files.iter().enumerate() {
            assert!(f == &files[0], "bake {k} differs from bake 0");
        }
    }

    #[test]
    fn large_bake_wraps_rows_and_round_trips() {
        let dir = test_dir("exr-rows");
        let path = dir.join("bake.exr");
        let v = bake(2 * MAX_WIDTH + 5);
        assert_eq!(layout_size(v.len()), (MAX_WIDTH, 3));
        write_exr(&path, &v, "big").unwrap();
        assert_bitwise_equal(&v, &read_exr(&path).unwrap());
    }

    #[test]
    fn empty_bake_round_trips() {
        let dir = test_dir("exr-empty");
        let path = dir.join("bake.exr");
        write_exr(&path, &VertexRadiosity::default(), "none").unwrap();
        let back = read_exr(&path).unwrap();
        assert_eq!(back.vertex_count, 0);
        assert!(back.positions.is_empty());
    }

    #[test]
    fn generic_reader_sees_channels_and_attributes() {
        let dir = test_dir("exr-generic");
        let path = dir.join("bake.exr");
        let v = bake(10);
        write_exr(&path, &v, "cornell").unwrap();
        let image = exr::prelude::read_all_data_from_file(&path).unwrap();
        assert_eq!(image.layer_data.len(), 1);
        let layer = &image.layer_data[0];
        assert_eq!((layer.size.x(), layer.size.y()), (10, 1));
        let names: Vec<String> = layer
            .channel_data
            .list
            .iter()
            .map(|c| c.name.to_string())
            .collect();
        for name in CHANNELS {
            assert!(
                names.iter().any(|n| n == name),
                "{name} missing from {names:?}"
            );
        }
        let other = &layer.attributes.other;
        assert_eq!(other.get(&text(ATTR_COUNT)), Some(&AttributeValue::I32(10)));
        assert_eq!(
            other.get(&text(ATTR_LAYOUT)),
            Some(&AttributeValue::Text(text(LAYOUT)))
        );
        assert_eq!(
            other.get(&text(ATTR_SCENE)),
            Some(&AttributeValue::Text(text("cornell")))
        );
    }

    #[test]
    fn plain_exr_is_rejected_with_a_reason() {
        let dir = test_dir("exr-plain");
        let path = dir.join("plain.exr");
        let channel = AnyChannel::new("R", FlatSamples::F32(vec![1.0; 4]));
        let channels: SmallVec<[AnyChannel<FlatSamples>; 4]> = std::iter::once(channel).collect();
        let layer = Layer::new(
            (2, 2),
            LayerAttributes::default(),
            Encoding::UNCOMPRESSED,
            AnyChannels::sort(channels),
        );
        Image::from_layer(layer).write().to_file(&path).unwrap();
        let err = read_exr(&path).unwrap_err();
        assert!(err.to_string().contains("not a radiosity bake"), "{err}");
        let err = read_exr(&dir.join("missing.exr")).unwrap_err();
        assert!(matches!(err, Error::Io { .. }), "{err:?}");
    }
}
