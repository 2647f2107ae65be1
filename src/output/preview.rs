//! Preview images: the per-vertex bake rendered by a small software rasterizer.
//!
//! The renderer is deliberately simple and exact about the few things it does:
//!
//! - **Camera.** A pinhole looking from `eye` at `target` with vertical field of view
//!   `vfov_deg`; image x runs along `forward × up` and image y along `up` (so world up is
//!   image up). Pixels are square.
//! - **Clipping.** Triangles are clipped in camera space against a near plane at a depth
//!   of `1e-4 ×` the farthest vertex depth (Sutherland and Hodgman, "Reentrant polygon
//!   clipping", CACM 1974), so a camera inside the scene sees partly-behind triangles cut,
//!   not dropped. Points behind the far side of the image are simply not covered.
//! - **Rasterization.** Edge functions at sample centres (Pineda, "A parallel algorithm for
//!   polygon rasterization", SIGGRAPH 1988), both windings drawn (scenes are often viewed
//!   from inside, and patch normals need not face the camera), a z-buffer on `1/z`, and
//!   perspective-correct interpolation of the vertex radiosity (attributes divided by depth,
//!   interpolated linearly in screen space, then divided by the interpolated `1/z`; Heckbert
//!   and Moreton, "Interpolation for polygon texture mapping and shading", 1991).
//! - **Anti-aliasing.** 2 × 2 supersampling: each pixel averages four samples, in linear
//!   light after exposure and clamping.
//! - **Exposure.** [`Exposure::Auto`] scales linear radiosity so that the 99th percentile of
//!   the luminance of covered samples (Rec. 709 luma weights 0.2126, 0.7152, 0.0722 on
//!   linear RGB) maps to 0.9, leaving out the samples of emitting surfaces (a lamp in view
//!   would otherwise set the exposure and darken the room) unless nothing else is in view;
//!   what is brighter clips to white.
//!   [`Exposure::Fixed`] uses the given scale.
//! - **Encoding.** Values are clamped to [0, 1] and encoded with the sRGB transfer function
//!   of IEC 61966-2-1 ([`srgb_oetf`]) to 8 bits. Uncovered pixels are dark grey.
//!
//! Rows of samples are rendered in parallel bands (rayon); each band walks the triangles in
//! mesh order with a strict depth test, so the image does not depend on the thread count.

use std::io::BufWriter;
use std::path::Path;

use glam::{DVec3, Vec3};
use rayon::prelude::*;

use super::vertex::VertexRadiosity;
use super::write_atomic;
use crate::error::{Error, Result};
use crate::scene::Camera;

/// Samples per pixel along each axis.
const SUPERSAMPLE: usize = 2;

/// Rows of samples per parallel band.
const BAND_ROWS: usize = 16;

/// Background colour (8-bit sRGB).
pub const BACKGROUND: [u8; 3] = [40, 40, 40];

/// Near plane depth as a fraction of the farthest vertex depth.
const NEAR_RELATIVE: f64 = 1e-4;

/// The luminance percentile [`Exposure::Auto`] maps to [`AUTO_TARGET`].
pub const AUTO_PERCENTILE: f64 = 0.99;

/// Display value [`Exposure::Auto`] gives the percentile luminance.
pub const AUTO_TARGET: f32 = 0.9;

/// How linear radiosity is scaled before display.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum Exposure {
    /// Scale so that the 99th percentile of the luminance of covered samples that do not
    /// emit becomes 0.9 (scale 1 when nothing lit is visible).
    #[default]
    Auto,
    /// Multiply linear radiosity by this factor.
    Fixed(f32),
}

/// An 8-bit sRGB image.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Pixels, row by row from the top, 3 bytes (R, G, B) each.
    pub rgb8: Vec<u8>,
    /// The exposure scale that was applied (the resolved value for [`Exposure::Auto`]); pass
    /// it to [`write_ply`](super::write_ply) for vertex colours that match the image.
    pub exposure: f32,
}

impl Image {
    /// The pixel at column `x`, row `y` (from the top).
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 3] {
        let k = (y as usize * self.width as usize + x as usize) * 3;
        [self.rgb8[k], self.rgb8[k + 1], self.rgb8[k + 2]]
    }
}

/// The sRGB transfer function (IEC 61966-2-1:1999, section 5.2): linear `c` in [0, 1] to
/// the encoded value, `12.92 c` up to 0.0031308 and `1.055 c^(1/2.4) - 0.055` above.
pub fn srgb_oetf(c: f32) -> f32 {
    let c = if c.is_nan() { 0.0 } else { c.clamp(0.0, 1.0) };
    if c <= 0.003_130_8 {
        12.92 * c
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}

/// The inverse of [`srgb_oetf`] (IEC 61966-2-1:1999, section 5.2).
pub fn srgb_eotf(v: f32) -> f32 {
    let v = v.clamp(0.0, 1.0);
    if v <= 0.040_45 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// Linear radiosity to 8-bit sRGB: scaled by `exposure`, clamped to [0, 1], encoded.
/// The preview and the PLY vertex colours both use it.
pub fn tone_map(rgb: [f32; 3], exposure: f32) -> [u8; 3] {
    rgb.map(|c| to_u8(srgb_oetf(c * exposure)))
}

/// [`crate::scene::luminance`] of an `f32` colour.
pub fn luminance(rgb: [f32; 3]) -> f32 {
    crate::scene::luminance(rgb.map(f64::from)) as f32
}

fn to_u8(v: f32) -> u8 {
    (v * 255.0 + 0.5).clamp(0.0, 255.0) as u8
}

/// A camera-space vertex: position (x right, y up, z forward) and radiosity.
#[derive(Clone, Copy, Debug)]
struct ClipVertex {
    p: DVec3,
    rgb: DVec3,
}

/// A triangle ready to rasterize, in sample coordinates.
#[derive(Clone, Copy, Debug)]
struct ScreenTriangle {
    /// Sample-space x, y of the corners.
    xy: [[f64; 2]; 3],
    /// `1 / z` of the corners.
    inv_z: [f64; 3],
    /// Radiosity divided by z at the corners.
    rgb_over_z: [DVec3; 3],
    /// Range of sample rows covered (inclusive), already clamped to the image.
    rows: (usize, usize),
    /// The triangle belongs to an emitting surface ([`VertexRadiosity::emits`]).
    emits: bool,
}

/// Renders `v` from `camera` at `width × height` pixels.
pub fn render_preview(
    v: &VertexRadiosity,
    camera: &Camera,
    width: u32,
    height: u32,
    exposure: Exposure,
) -> Image {
    let (w, h) = (width as usize * SUPERSAMPLE, height as usize * SUPERSAMPLE);
    let triangles = if w == 0 || h == 0 {
        Vec::new()
    } else {
        project(v, camera, w, h)
    };

    // Linear radiosity per sample, and whether the sample is covered.
    let mut color = vec![[0.0f32; 3]; w * h];
    let mut depth = vec![0.0f64; w * h]; // 1/z; 0 = nothing (infinitely far)
    let mut emits = vec![false; w * h];
    let band = BAND_ROWS * w.max(1);
    color
        .par_chunks_mut(band)
        .zip(depth.par_chunks_mut(band))
        .zip(emits.par_chunks_mut(band))
        .enumerate()
        .for_each(|(band, ((color, depth), emits))| {
            let y0 = band * BAND_ROWS;
            let y1 = y0 + color.len() / w.max(1); // exclusive
            let mut out = Samples {
                color,
                depth,
                emits,
            };
            for t in triangles.iter().filter(|t| t.rows.0 < y1 && t.rows.1 >= y0) {
                raster(t, w, y0, y1, &mut out);
            }
        });

    let scale = match exposure {
        Exposure::Fixed(s) => s,
        Exposure::Auto => auto_exposure(&color, &depth, &emits),
    };
    let bg = BACKGROUND.map(|c| srgb_eotf(f32::from(c) / 255.0));
    let mut rgb8 = vec![0u8; width as usize * height as usize * 3];
    rgb8.par_chunks_mut((width as usize * 3).max(1))
        .enumerate()
        .for_each(|(py, row)| {
            for (px, out) in row.chunks_mut(3).enumerate() {
                let mut sum = [0.0f32; 3];
                for sy in 0..SUPERSAMPLE {
                    for sx in 0..SUPERSAMPLE {
                        let k = (py * SUPERSAMPLE + sy) * w + px * SUPERSAMPLE + sx;
                        let c = if depth[k] > 0.0 {
                            color[k].map(|c| (c * scale).clamp(0.0, 1.0))
                        } else {
                            bg
                        };
                        for ch in 0..3 {
                            sum[ch] += c[ch];
                        }
                    }
                }
                let n = (SUPERSAMPLE * SUPERSAMPLE) as f32;
                for ch in 0..3 {
                    out[ch] = to_u8(srgb_oetf(sum[ch] / n));
                }
            }
        });
    Image {
        width,
        height,
        rgb8,
        exposure: scale,
    }
}

/// One band's sample buffers: linear radiosity, `1/z` (0: uncovered), and whether the
/// nearest surface emits.
struct Samples<'a> {
    color: &'a mut [[f32; 3]],
    depth: &'a mut [f64],
    emits: &'a mut [bool],
}

/// The [`Exposure::Auto`] scale for the covered samples (see the module docs): those of
/// emitting surfaces are left out (a lamp in view would darken the room), unless nothing
/// else is covered.
fn auto_exposure(color: &[[f32; 3]], depth: &[f64], emits: &[bool]) -> f32 {
    let covered = |skip_emitters: bool| -> Vec<f32> {
        color
            .iter()
            .zip(depth)
            .zip(emits)
            .filter(|((_, &d), &e)| d > 0.0 && !(skip_emitters && e))
            .map(|((c, _), _)| luminance(*c))
            .filter(|l| l.is_finite())
            .collect()
    };
    let mut lum = covered(true);
    if lum.is_empty() {
        lum = covered(false);
    }
    if lum.is_empty() {
        return 1.0;
    }
    let k = ((lum.len() - 1) as f64 * AUTO_PERCENTILE).round() as usize;
    let (_, &mut p, _) = lum.select_nth_unstable_by(k, f32::total_cmp);
    if p > 0.0 {
        AUTO_TARGET / p
    } else {
        1.0
    }
}

/// Camera basis: (right, up, forward), orthonormal; falls back to sane axes when the
/// camera is degenerate (eye on target, up along the view direction).
fn basis(camera: &Camera) -> (DVec3, DVec3, DVec3) {
    let forward = (camera.target - camera.eye)
        .as_dvec3()
        .try_normalize()
        .unwrap_or(DVec3::Z);
    let up = camera.up.as_dvec3();
    let right = forward
        .cross(up)
        .try_normalize()
        .or_else(|| forward.cross(DVec3::Y).try_normalize())
        .or_else(|| forward.cross(DVec3::X).try_normalize())
        .unwrap_or(DVec3::X);
    (right, right.cross(forward), forward)
}

/// Transforms, clips and projects every triangle of `v` to a `w × h` sample grid.
fn project(v: &VertexRadiosity, camera: &Camera, w: usize, h: usize) -> Vec<ScreenTriangle> {
    let (right, up, forward) = basis(camera);
    let eye = camera.eye.as_dvec3();
    let to_camera = |p: Vec3| {
        let d = p.as_dvec3() - eye;
        DVec3::new(d.dot(right), d.dot(up), d.dot(forward))
    };
    let cam: Vec<DVec3> = v.positions.iter().map(|&p| to_camera(p)).collect();
    let far = cam
        .iter()
        .map(|p| p.z)
        .filter(|z| z.is_finite())
        .fold(0.0f64, f64::max);
    if far <= 0.0 {
        return Vec::new();
    }
    let near = far * NEAR_RELATIVE;
    let vfov = f64::from(camera.vfov_deg).clamp(1.0, 179.0).to_radians();
    // Sample-space scale: a camera-space slope of tan(vfov / 2) reaches the image edge.
    let focal = h as f64 * 0.5 / (vfov * 0.5).tan();
    let (cx, cy) = (w as f64 * 0.5, h as f64 * 0.5);

    v.triangles
        .par_iter()
        .enumerate()
        .filter(|&(ti, t)| {
            // Of the two sides of a two-sided face (one on the other), only the one facing
            // the eye: drawing both would leave which one shows to rounding.
            if !v.two_sided.get(ti).copied().unwrap_or(false) {
                return true;
            }
            let [a, b, c] = t.map(|k| v.positions.get(k as usize).copied().unwrap_or(Vec3::NAN));
            (b - a)
                .as_dvec3()
                .cross((c - a).as_dvec3())
                .dot(a.as_dvec3() - eye)
                <= 0.0
        })
        .flat_map_iter(|(ti, t)| {
            let emits = v.emits.get(ti).copied().unwrap_or(false);
            let corner = |k: usize| {
                let i = t[k] as usize;
                let c = v.rgb.get(i).copied().unwrap_or([0.0; 3]);
                ClipVertex {
                    p: cam.get(i).copied().unwrap_or(DVec3::NAN),
                    rgb: DVec3::new(c[0].into(), c[1].into(), c[2].into()),
                }
            };
            let poly = clip_near([corner(0), corner(1), corner(2)], near);
            let screen: Vec<([f64; 2], f64, DVec3)> = poly
                .iter()
                .map(|c| {
                    let inv_z = 1.0 / c.p.z;
                    let xy = [cx + focal * c.p.x * inv_z, cy - focal * c.p.y * inv_z];
                    (xy, inv_z, c.rgb * inv_z)
                })
                .collect();
            // Fan triangulation of the clipped convex polygon.
            (1..screen.len().saturating_sub(1)).filter_map(move |k| {
                let s = [screen[0], screen[k], screen[k + 1]];
                let xy = [s[0].0, s[1].0, s[2].0];
                let ys = xy.map(|p| p[1]);
                let (y_lo, y_hi) = (ys[0].min(ys[1]).min(ys[2]), ys[0].max(ys[1]).max(ys[2]));
                if !(y_lo.is_finite() && y_hi.is_finite()) || y_hi < 0.0 || y_lo > h as f64 {
                    return None;
                }
                let rows = ((y_lo - 0.5).ceil().max(0.0) as usize, {
                    let last = (y_hi - 0.5).floor();
                    if last < 0.0 {
                        return None;
                    }
                    (last as usize).min(h - 1)
                });
                Some(ScreenTriangle {
                    xy,
                    inv_z: [s[0].1, s[1].1, s[2].1],
                    rgb_over_z: [s[0].2, s[1].2, s[2].2],
                    rows,
                    emits,
                })
            })
        })
        .collect()
}

/// Clips a camera-space triangle to `z >= near` (Sutherland-Hodgman against one plane);
/// returns the convex polygon left, 0, 3 or 4 corners.
fn clip_near(tri: [ClipVertex; 3], near: f64) -> Vec<ClipVertex> {
    let mut out = Vec::with_capacity(4);
    for k in 0..3 {
        let (a, b) = (tri[k], tri[(k + 1) % 3]);
        let (a_in, b_in) = (a.p.z >= near, b.p.z >= near);
        if a_in {
            out.push(a);
        }
        if a_in != b_in {
            let t = (near - a.p.z) / (b.p.z - a.p.z);
            let mut p = a.p.lerp(b.p, t);
            p.z = near; // exactly on the plane despite rounding
            out.push(ClipVertex {
                p,
                rgb: a.rgb.lerp(b.rgb, t),
            });
        }
    }
    out
}

/// Draws triangle `t` into the sample rows `y0..y1` (`color` and `depth` hold those rows).
fn raster(t: &ScreenTriangle, w: usize, y0: usize, y1: usize, out: &mut Samples) {
    let [a, b, c] = t.xy;
    // Twice the signed area; either sign is drawn (no back-face culling).
    let area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
    if area == 0.0 || !area.is_finite() {
        return;
    }
    let inv_area = 1.0 / area;
    let xs = [a[0], b[0], c[0]];
    let x_lo = xs[0].min(xs[1]).min(xs[2]);
    let x_hi = xs[0].max(xs[1]).max(xs[2]);
    if x_hi < 0.0 || x_lo > w as f64 {
        return;
    }
    let sx0 = (x_lo - 0.5).ceil().max(0.0) as usize;
    let sx1 = ((x_hi - 0.5).floor().max(-1.0) + 1.0).min(w as f64) as usize; // exclusive
    let edge = |p: [f64; 2], q: [f64; 2], x: f64, y: f64| {
        (q[0] - p[0]) * (y - p[1]) - (q[1] - p[1]) * (x - p[0])
    };
    for sy in t.rows.0.max(y0)..=t.rows.1.min(y1 - 1) {
        let y = sy as f64 + 0.5;
        let row = (sy - y0) * w;
        for sx in sx0..sx1 {
            let x = sx as f64 + 0.5;
            // Barycentric weights, normalised by the signed area so both windings work.
            let l0 = edge(b, c, x, y) * inv_area;
            let l1 = edge(c, a, x, y) * inv_area;
            let l2 = edge(a, b, x, y) * inv_area;
            if l0 < 0.0 || l1 < 0.0 || l2 < 0.0 {
                continue;
            }
            let inv_z = l0 * t.inv_z[0] + l1 * t.inv_z[1] + l2 * t.inv_z[2];
            let k = row + sx;
            if inv_z > out.depth[k] {
                out.depth[k] = inv_z;
                let rgb =
                    (t.rgb_over_z[0] * l0 + t.rgb_over_z[1] * l1 + t.rgb_over_z[2] * l2) / inv_z;
                out.color[k] = [rgb.x as f32, rgb.y as f32, rgb.z as f32];
                out.emits[k] = t.emits;
            }
        }
    }
}

/// Writes `image` to `path` as an 8-bit RGB PNG tagged sRGB (atomically).
pub fn write_png(path: &Path, image: &Image) -> Result<()> {
    let expected = image.width as usize * image.height as usize * 3;
    if image.rgb8.len() != expected || expected == 0 {
        return Err(Error::Output {
            path: path.to_path_buf(),
            msg: format!(
                "cannot write a {} x {} image from {} bytes",
                image.width,
                image.height,
                image.rgb8.len()
            ),
        });
    }
    write_atomic(path, |tmp| {
        let file = std::fs::File::create(tmp).map_err(|e| Error::io(tmp, e))?;
        let png_error = |e: png::EncodingError| match e {
            png::EncodingError::IoError(source) => Error::io(tmp, source),
            e => Error::Output {
                path: tmp.to_path_buf(),
                msg: format!("PNG encoder: {e}"),
            },
        };
        let mut encoder = png::Encoder::new(BufWriter::new(file), image.width, image.height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
        let mut writer = encoder.write_header().map_err(png_error)?;
        writer.write_image_data(&image.rgb8).map_err(png_error)?;
        writer.finish().map_err(png_error)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::test_dir;

    fn camera() -> Camera {
        Camera {
            eye: Vec3::new(0.0, 0.0, -5.0),
            target: Vec3::ZERO,
            up: Vec3::Y,
            vfov_deg: 60.0,
        }
    }

    /// One triangle in the plane z = 0 with the given corners' radiosity.
    fn triangle(p: [Vec3; 3], rgb: [[f32; 3]; 3]) -> VertexRadiosity {
        VertexRadiosity {
            two_sided: Vec::new(),
            positions: p.to_vec(),
            normals: vec![Vec3::NEG_Z; 3],
            rgb: rgb.to_vec(),
            triangles: vec![[0, 1, 2]],
            patch_of_triangle: vec![0],
            emits: Vec::new(),
        }
    }

    fn is_background(p: [u8; 3]) -> bool {
        p == BACKGROUND
    }

    #[test]
    fn big_triangle_covers_centre_not_corners() {
        let v = triangle(
            [
                Vec3::new(-2.0, -1.5, 0.0),
                Vec3::new(2.0, -1.5, 0.0),
                Vec3::new(0.0, 2.0, 0.0),
            ],
            [[1.0, 0.5, 0.25]; 3],
        );
        for tri in [
            v.clone(),
            VertexRadiosity {
                triangles: vec![[0, 2, 1]],
                ..v.clone()
            },
        ] {
            let img = render_preview(&tri, &camera(), 64, 48, Exposure::Fixed(0.5));
            assert!(!is_background(img.pixel(32, 24)));
            // Fixed exposure: 0.5 × (1, 0.5, 0.25) encoded as sRGB.
            assert_eq!(img.pixel(32, 24), tone_map([1.0, 0.5, 0.25], 0.5));
            for (x, y) in [(0, 0), (63, 0), (0, 47), (63, 47)] {
                assert!(is_background(img.pixel(x, y)), "corner {x},{y}");
            }
        }
    }

    #[test]
    fn auto_exposure_maps_flat_field_to_target() {
        let v = triangle(
            [
                Vec3::new(-2.0, -1.5, 0.0),
                Vec3::new(2.0, -1.5, 0.0),
                Vec3::new(0.0, 2.0, 0.0),
            ],
            [[40.0; 3]; 3],
        );
        let img = render_preview(&v, &camera(), 32, 32, Exposure::Auto);
        assert!((img.exposure - AUTO_TARGET / 40.0).abs() < 1e-6);
        assert_eq!(img.pixel(16, 16), [to_u8(srgb_oetf(AUTO_TARGET)); 3]);
    }

    #[test]
    fn world_up_is_image_up_and_right_is_right() {
        // A triangle in the upper-left quadrant as seen from the camera. The camera looks
        // along +z with y up, so its right is -x.
        let v = triangle(
            [
                Vec3::new(0.2, 0.2, 0.0),
                Vec3::new(2.0, 0.2, 0.0),
                Vec3::new(0.2, 2.0, 0.0),
            ],
            [[1.0; 3]; 3],
        );
        let img = render_preview(&v, &camera(), 64, 64, Exposure::Fixed(1.0));
        assert!(!is_background(img.pixel(24, 24)));
        assert!(is_background(img.pixel(40, 24)));
        assert!(is_background(img.pixel(24, 40)));
    }

    #[test]
    fn nearer_triangle_hides_farther() {
        let far = [
            Vec3::new(-3.0, -3.0, 1.0),
            Vec3::new(3.0, -3.0, 1.0),
            Vec3::new(0.0, 3.0, 1.0),
        ];
        let near = far.map(|p| p - Vec3::Z * 2.0);
        for order in [[0u32, 1, 2, 3, 4, 5], [3, 4, 5, 0, 1, 2]] {
            let mut positions = far.to_vec();
            positions.extend(near);
            let v = VertexRadiosity {
                two_sided: Vec::new(),
                positions,
                normals: vec![Vec3::Z; 6],
                rgb: [[1.0, 0.0, 0.0]; 3]
                    .into_iter()
                    .chain([[0.0, 0.0, 1.0]; 3])
                    .collect(),
                triangles: vec![
                    [order[0], order[1], order[2]],
                    [order[3], order[4], order[5]],
                ],
                patch_of_triangle: vec![0, 1],
                emits: Vec::new(),
            };
            let img = render_preview(&v, &camera(), 32, 32, Exposure::Fixed(1.0));
            assert_eq!(img.pixel(16, 16), [0, 0, 255]);
        }
    }

    #[test]
    fn auto_exposure_leaves_emitters_out() {
        // A lamp (radiosity 50) beside a wall (0.2), each covering half the view.
        let v = VertexRadiosity {
            two_sided: Vec::new(),
            positions: vec![
                Vec3::new(-9.0, -9.0, 0.0),
                Vec3::new(0.0, -9.0, 0.0),
                Vec3::new(0.0, 9.0, 0.0),
                Vec3::new(-9.0, 9.0, 0.0),
                Vec3::new(9.0, -9.0, 0.0),
                Vec3::new(9.0, 9.0, 0.0),
            ],
            normals: vec![-Vec3::Z; 6],
            rgb: vec![
                [50.0; 3], [50.0; 3], [50.0; 3], [50.0; 3], // lamp corners 0-3
                [0.2; 3], [0.2; 3],
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]],
            patch_of_triangle: vec![0, 0, 1, 1],
            emits: vec![true, true, false, false],
        };
        // Vertices 1 and 2 are shared with the lamp: give the wall its own copies.
        let mut v = v;
        v.positions
            .extend([Vec3::new(0.0, -9.0, 0.0), Vec3::new(0.0, 9.0, 0.0)]);
        v.normals.extend([-Vec3::Z; 2]);
        v.rgb.extend([[0.2; 3]; 2]);
        v.triangles[2] = [6, 4, 5];
        v.triangles[3] = [6, 5, 7];
        let img = render_preview(&v, &camera(), 32, 32, Exposure::Auto);
        assert!(
            (img.exposure - AUTO_TARGET / 0.2).abs() < 1e-4,
            "{}",
            img.exposure
        );
        // Without the flags the lamp sets the exposure and the wall goes dark.
        let blind = VertexRadiosity {
            emits: Vec::new(),
            ..v.clone()
        };
        let img = render_preview(&blind, &camera(), 32, 32, Exposure::Auto);
        assert!(
            (img.exposure - AUTO_TARGET / 50.0).abs() < 1e-6,
            "{}",
            img.exposure
        );
        // Only the lamp in view: it is what the exposure has.
        let lamp = VertexRadiosity {
            triangles: v.triangles[..2].to_vec(),
            patch_of_triangle: vec![0, 0],
            emits: vec![true, true],
            ..v.clone()
        };
        let img = render_preview(&lamp, &camera(), 32, 32, Exposure::Auto);
        assert!(
            (img.exposure - AUTO_TARGET / 50.0).abs() < 1e-6,
            "{}",
            img.exposure
        );
    }

    #[test]
    fn perspective_correct_interpolation() {
        // A floor strip receding from the camera, radiosity 0 at the near edge and 1 at the
        // far edge. Linear in world space: the image row showing depth z must show (z-1)/8,
        // not the screen-space lerp.
        let (z0, z1) = (1.0f32, 9.0f32);
        let v = VertexRadiosity {
            two_sided: Vec::new(),
            positions: vec![
                Vec3::new(-50.0, -1.0, z0),
                Vec3::new(50.0, -1.0, z0),
                Vec3::new(50.0, -1.0, z1),
                Vec3::new(-50.0, -1.0, z1),
            ],
            normals: vec![Vec3::Y; 4],
            rgb: vec![[0.0; 3], [0.0; 3], [1.0; 3], [1.0; 3]],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            patch_of_triangle: vec![0, 0],
            emits: Vec::new(),
        };
        let cam = Camera {
            eye: Vec3::ZERO,
            target: Vec3::Z,
            up: Vec3::Y,
            vfov_deg: 90.0,
        };
        let (w, h) = (8u32, 200u32);
        let img = render_preview(&v, &cam, w, h, Exposure::Fixed(1.0));
        // Image row y (pixel centre) sees the floor y = -1 at depth z = focal / (y - h/2).
        let focal = f64::from(h) * 0.5; // tan(45 deg) = 1
        let y = 120u32;
        let z = focal / (f64::from(y) + 0.5 - f64::from(h) * 0.5);
        let expect = ((z - f64::from(z0)) / f64::from(z1 - z0)) as f32;
        let got = srgb_eotf(f32::from(img.pixel(4, y)[0]) / 255.0);
        assert!((got - expect).abs() < 0.02, "row {y}: {got} vs {expect}");
    }

    #[test]
    fn triangle_crossing_near_plane_is_clipped_not_dropped() {
        // Camera inside a floor triangle's extent: one corner is far behind the camera.
        let v = triangle(
            [
                Vec3::new(-10.0, -1.0, -10.0),
                Vec3::new(10.0, -1.0, -10.0),
                Vec3::new(0.0, -1.0, 10.0),
            ],
            [[1.0; 3]; 3],
        );
        let cam = Camera {
            eye: Vec3::ZERO,
            target: Vec3::Z,
            up: Vec3::Y,
            vfov_deg: 90.0,
        };
        let img = render_preview(&v, &cam, 40, 40, Exposure::Fixed(1.0));
        // The floor fills the lower half below the horizon, down to the bottom edge.
        assert!(!is_background(img.pixel(20, 39)));
        assert!(!is_background(img.pixel(20, 25)));
        assert!(is_background(img.pixel(20, 10)));
    }

    #[test]
    fn srgb_curve_matches_the_standard() {
        assert_eq!(srgb_oetf(0.0), 0.0);
        assert!((srgb_oetf(1.0) - 1.0).abs() < 1e-6);
        assert!((srgb_oetf(0.18) - 0.4614).abs() < 1e-3);
        for k in 0..=100 {
            let c = k as f32 / 100.0;
            assert!((srgb_eotf(srgb_oetf(c)) - c).abs() < 1e-5);
        }
    }

    #[test]
    fn degenerate_inputs_do_not_panic() {
        let v = triangle([Vec3::ZERO; 3], [[1.0; 3]; 3]);
        let cam = Camera {
            eye: Vec3::ZERO,
            target: Vec3::ZERO,
            up: Vec3::ZERO,
            vfov_deg: 0.0,
        };
        let img = render_preview(&v, &cam, 5, 3, Exposure::Auto);
        assert_eq!(img.rgb8.len(), 45);
        let img = render_preview(&VertexRadiosity::default(), &camera(), 0, 0, Exposure::Auto);
        assert!(img.rgb8.is_empty());
        let err = write_png(&test_dir("png-empty").join("a.png"), &img).unwrap_err();
        assert!(matches!(err, Error::Output { .. }));
    }

    #[test]
    fn cornell_box_from_its_camera() {
        // Radiosity = reflectance falling off away from the light, plus emission on the
        // light: the red wall (x = 556) must appear on the left, the green wall (x = 0) on
        // the right, the light at the top.
        let scene = crate::scene::Scene::load("cornell").unwrap();
        let set =
            crate::mesh::PatchSet::build(&scene, crate::mesh::Resolution::Patches(1000)).unwrap();
        let b: Vec<[f64; 3]> = (0..set.len())
            .map(|i| {
                let (r, e) = (set.rho(i), set.emit(i));
                let d = set.centroid[i].distance(glam::DVec3::new(278.0, 548.8, 279.5)) / 400.0;
                let f = 1.0 / (1.0 + d * d);
                [r[0] * f + e[0], r[1] * f + e[1], r[2] * f + e[2]]
            })
            .collect();
        let v = crate::output::interpolate(&set, &b, crate::output::DEFAULT_CREASE_DEG);
        let img = render_preview(
            &v,
            &scene.camera_or_framing(),
            256,
            256,
            Exposure::Fixed(1.0),
        );
        if let Some(dir) = std::env::var_os("RADIOSITY_TEST_IMAGES") {
            write_png(&Path::new(&dir).join("cornell-preview.png"), &img).unwrap();
        }
        let left = img.pixel(20, 128);
        let right = img.pixel(235, 128);
        assert!(
            left[0] > left[1] + 60 && left[0] > left[2] + 60,
            "left wall {left:?}"
        );
        assert!(
            right[1] > right[0] + 40 && right[1] > right[2] + 40,
            "right wall {right:?}"
        );
        // The light, on the ceiling near the top centre, clips to white.
        let top = (0..60)
            .map(|y| img.pixel(128, y))
            .find(|p| *p == [255, 255, 255]);
        assert!(top.is_some(), "no light at the top of the image");
        // The camera sees the whole box front-on: no background inside the frame.
        assert!(!is_background(img.pixel(128, 128)));
    }

    #[test]
    fn png_round_trip() {
        let v = triangle(
            [
                Vec3::new(-2.0, -1.5, 0.0),
                Vec3::new(2.0, -1.5, 0.0),
                Vec3::new(0.0, 2.0, 0.0),
            ],
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        );
        let img = render_preview(&v, &camera(), 40, 30, Exposure::Auto);
        let path = test_dir("png").join("t.png");
        write_png(&path, &img).unwrap();
        let decoder = png::Decoder::new(std::fs::File::open(&path).unwrap());
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (40, 30));
        assert_eq!(&buf[..info.buffer_size()], &img.rgb8[..]);
    }
}
