//! The per-vertex bake as a binary PLY mesh, for Blender, MeshLab and similar tools.
//!
//! Format: PLY 1.0, `binary_little_endian` (Turk, "The PLY Polygon File Format", 1994;
//! the header keywords and property names are the ones Blender and MeshLab import):
//!
//! ```text
//! ply
//! format binary_little_endian 1.0
//! comment radiosity <version> per-vertex radiosity; red green blue = sRGB at exposure <e>
//! comment units <mm | cm | m | not given ...>
//! comment up +y
//! element vertex <n>
//! property float x
//! property float y
//! property float z
//! property float nx
//! property float ny
//! property float nz
//! property uchar red
//! property uchar green
//! property uchar blue
//! property float radiosity_r
//! property float radiosity_g
//! property float radiosity_b
//! property float quality
//! element face <m>
//! property list uchar int vertex_indices
//! end_header
//! ```
//!
//! `red green blue` are display colours made by the same tone mapping as the preview
//! ([`tone_map`]: exposure, clamp, sRGB); `radiosity_*` are the linear values, `quality` their luminance
//! ([`crate::scene::luminance`]: MeshLab keeps only the 8-bit colours of a PLY, but colours
//! and filters by `quality`). Positions
//! are in the scene's units, as loaded (the `units` comment names them when the scene or
//! `--units` does), with +Y up, the OBJ convention; `mesh.glb` has the same mesh in
//! metres ([`super::gltf`]).
//!
//! [`write_ply_with`] writes the same layout with other colours, other float properties in
//! place of `radiosity_*` and another comment (the thermal mode's `mesh.ply`).

use std::io::{BufWriter, Write};
use std::path::Path;

use super::preview::tone_map;
use super::vertex::VertexRadiosity;
use super::write_atomic;
use crate::error::{Error, Result};
use crate::scene::Units;

/// The up-axis comment of every PLY written here.
pub const UP: &str = "up +y";

/// Writes `v` to `path` as a binary little-endian PLY with vertex colours tone-mapped at
/// `exposure` (a linear scale, e.g. [`Image::exposure`](super::Image::exposure)); `units`
/// is the scene's length unit, when known, for the header.
pub fn write_ply(
    path: &Path,
    v: &VertexRadiosity,
    exposure: f32,
    units: Option<Units>,
) -> Result<()> {
    v.checked_len(path)?;
    let colours: Vec<[u8; 3]> = v.rgb.iter().map(|&c| tone_map(c, exposure)).collect();
    let plane = |c: usize| -> Vec<f32> { v.rgb.iter().map(|x| x[c]).collect() };
    let (r, g, b) = (plane(0), plane(1), plane(2));
    let quality: Vec<f32> = v
        .rgb
        .iter()
        .map(|&c| super::preview::luminance(c))
        .collect();
    let comment = format!(
        "radiosity {} per-vertex radiosity; red green blue = sRGB at exposure {exposure}",
        env!("CARGO_PKG_VERSION")
    );
    let units = match units {
        Some(u) => format!("units {}", u.symbol()),
        None => "units not given (no #@units line in the scene, no --units)".to_string(),
    };
    write_ply_with(
        path,
        v,
        &[&comment, &units, UP],
        &colours,
        &[
            ("radiosity_r", &r),
            ("radiosity_g", &g),
            ("radiosity_b", &b),
            ("quality", &quality),
        ],
    )
}

/// Writes the mesh of `v` (positions, normals, triangles; `v.rgb` is not written) as a
/// binary little-endian PLY whose vertices carry `x y z nx ny nz`, the 8-bit `red green
/// blue` of `colours`, then the float properties `values` (name, one value per vertex), in
/// that order, with a header line `comment <c>` for each of `comments`. The generic layer under
/// [`write_ply`] and the thermal mode's `mesh.ply`.
pub fn write_ply_with(
    path: &Path,
    v: &VertexRadiosity,
    comments: &[&str],
    colours: &[[u8; 3]],
    values: &[(&str, &[f32])],
) -> Result<()> {
    let n = v.checked_len(path)?;
    let refuse = |msg: String| {
        Err(Error::Output {
            path: path.to_path_buf(),
            msg,
        })
    };
    if n > i32::MAX as usize {
        return refuse(format!("{n} vertices are too many for PLY int indices"));
    }
    if colours.len() != n {
        return refuse(format!("{} colours for {n} vertices", colours.len()));
    }
    if let Some((name, x)) = values.iter().find(|(_, x)| x.len() != n) {
        return refuse(format!(
            "property `{name}` has {} values for {n} vertices",
            x.len()
        ));
    }
    if comments.iter().any(|c| c.contains(['\n', '\r'])) {
        return refuse("a PLY comment must be one line".into());
    }
    if let Some(t) = v
        .triangles
        .iter()
        .find(|t| t.iter().any(|&k| k as usize >= n))
    {
        return refuse(format!(
            "triangle {t:?} refers to a vertex beyond the {n} vertices"
        ));
    }
    let names: Vec<&str> = values.iter().map(|(name, _)| *name).collect();
    let head = header(n, v.triangles.len(), comments, &names);
    write_atomic(path, |tmp| {
        let file = std::fs::File::create(tmp).map_err(|e| Error::io(tmp, e))?;
        let mut w = BufWriter::new(file);
        write_body(&mut w, &head, v, colours, values).map_err(|e| Error::io(tmp, e))?;
        w.into_inner().map_err(|e| Error::io(tmp, e.into_error()))?;
        Ok(())
    })
}

/// The PLY header for `vertices` and `faces` with the float properties `values` after the
/// colours (see the module docs).
fn header(vertices: usize, faces: usize, comments: &[&str], values: &[&str]) -> String {
    let mut h = String::from("ply\nformat binary_little_endian 1.0\n");
    for c in comments {
        h += &format!("comment {c}\n");
    }
    h += &format!("element vertex {vertices}\n");
    for p in ["x", "y", "z", "nx", "ny", "nz"] {
        h += &format!("property float {p}\n");
    }
    for p in ["red", "green", "blue"] {
        h += &format!("property uchar {p}\n");
    }
    for p in values {
        h += &format!("property float {p}\n");
    }
    h += &format!("element face {faces}\nproperty list uchar int vertex_indices\nend_header\n");
    h
}

fn write_body(
    w: &mut impl Write,
    head: &str,
    v: &VertexRadiosity,
    colours: &[[u8; 3]],
    values: &[(&str, &[f32])],
) -> std::io::Result<()> {
    w.write_all(head.as_bytes())?;
    for k in 0..v.positions.len() {
        let (p, n) = (v.positions[k], v.normals[k]);
        for x in [p.x, p.y, p.z, n.x, n.y, n.z] {
            w.write_all(&x.to_le_bytes())?;
        }
        w.write_all(&colours[k])?;
        for (_, x) in values {
            w.write_all(&x[k].to_le_bytes())?;
        }
    }
    for t in &v.triangles {
        w.write_all(&[3u8])?;
        for &k in t {
            // Checked above: every index fits in an i32.
            w.write_all(&(k as i32).to_le_bytes())?;
        }
    }
    w.flush()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::test_dir;
    use glam::Vec3;

    fn quad() -> VertexRadiosity {
        VertexRadiosity {
            two_sided: Vec::new(),
            positions: vec![
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(1.0, 0.0, 0.0),
                Vec3::new(1.0, 1.0, 0.0),
                Vec3::new(0.0, 1.0, 0.0),
            ],
            normals: vec![Vec3::Z; 4],
            rgb: vec![[0.0; 3], [0.5, 0.25, 0.125], [1.0; 3], [2.0, 0.0, 0.0]],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            patch_of_triangle: vec![0, 0],
            emits: Vec::new(),
        }
    }

    #[test]
    fn header_and_body_parse_back() {
        let v = quad();
        let path = test_dir("ply").join("bake.ply");
        write_ply(&path, &v, 1.0, Some(Units::Millimetres)).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let end = b"end_header\n";
        let at = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
        let head = std::str::from_utf8(&bytes[..at]).unwrap();
        let lines: Vec<&str> = head.lines().collect();
        assert_eq!(lines[0], "ply");
        assert_eq!(lines[1], "format binary_little_endian 1.0");
        assert!(lines.contains(&"element vertex 4"));
        assert!(lines.contains(&"element face 2"));
        assert!(lines.contains(&"property uchar red"));
        assert!(lines.contains(&"property float radiosity_b"));
        assert!(lines.contains(&"property float quality"));
        assert!(lines.contains(&"property list uchar int vertex_indices"));
        assert_eq!(lines[3..5], ["comment units mm", "comment up +y"]);
        // Vertex record: 6 floats, 3 bytes, 4 floats; face record: 1 + 3 x 4 bytes.
        let vertex_size = 6 * 4 + 3 + 4 * 4;
        assert_eq!(bytes.len() - at, 4 * vertex_size + 2 * 13);
        let body = &bytes[at..];
        let f32_at = |o: usize| f32::from_le_bytes(body[o..o + 4].try_into().unwrap());
        // Vertex 1: position, colour, linear radiosity.
        let v1 = vertex_size;
        assert_eq!(f32_at(v1), 1.0);
        assert_eq!(&body[v1 + 24..v1 + 27], &tone_map([0.5, 0.25, 0.125], 1.0));
        assert_eq!(f32_at(v1 + 27), 0.5);
        // Its quality: the luminance of (0.5, 0.25, 0.125).
        let y = 0.2126 * 0.5 + 0.7152 * 0.25 + 0.0722 * 0.125;
        assert!(
            (f64::from(f32_at(v1 + 39)) - y).abs() < 1e-7,
            "{}",
            f32_at(v1 + 39)
        );
        assert_eq!(
            &body[2 * vertex_size + 24..2 * vertex_size + 27],
            &[255, 255, 255]
        );
        // Second face.
        let f1 = 4 * vertex_size + 13;
        assert_eq!(body[f1], 3);
        let idx: Vec<i32> = (0..3)
            .map(|k| i32::from_le_bytes(body[f1 + 1 + 4 * k..f1 + 5 + 4 * k].try_into().unwrap()))
            .collect();
        assert_eq!(idx, [0, 2, 3]);
    }

    #[test]
    fn bad_indices_are_refused() {
        let mut v = quad();
        v.triangles.push([0, 1, 9]);
        let path = test_dir("ply-bad").join("bake.ply");
        assert!(matches!(
            write_ply(&path, &v, 1.0, None),
            Err(Error::Output { .. })
        ));
        assert!(!path.exists());
    }
}
