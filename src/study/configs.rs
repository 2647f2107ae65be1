//! The study's configurations: small in-memory scenes whose form factor `F_ij` is known in
//! closed form.
//!
//! Two exact superposition rules extend the catalogue to offset rectangles. Both rest on
//! the kernel depending only on coordinate *differences* along the directions in which the
//! rectangles are offset (Siegel and Howell, "configuration-factor algebra"; Howell's
//! catalogue C-12 and C-16 are built the same way):
//!
//! - **Along a common line** (`along_line`): two rectangles of fixed widths in two fixed
//!   planes, spanning `[a1, a2]` and `[b1, b2]` along a line parallel to both. With
//!   `k(za - zb)` the kernel integrated over the widths, `Q = A_1 F_12 = ∫∫ k(za - zb)`, and
//!   with `Φ'' = k`, `Φ(0) = Φ'(0) = 0`,
//!   `Q = Φ(a2 - b1) + Φ(a1 - b2) - Φ(a2 - b2) - Φ(a1 - b1)`.
//!   For `[0, x]` against `[0, x]` this is `2 Φ(x)`, so `Φ(x) = G(x)/2` where `G(x)` is
//!   `A F` of the aligned pair of length `x`, a catalogue entry (C-11 or C-14). `Φ` is even.
//! - **Parallel planes** ([`parallel_offset`]): the same rule in both in-plane directions,
//!   `Q = Σ s s' Φ2(a_i - b_k, c_j - d_l)` with `Φ2(x, y) = G(x, y)/4` and
//!   `G(x, y) = x y F_C-11(x, y, h)`.
//!
//! The unit tests check both against an independent Gauss–Legendre integration of the
//! exact point-to-polygon factor.

use glam::DVec3;

use crate::analytic::{parallel_rectangles, perpendicular_rectangles};
use crate::scene::{Face, Material, Scene};

/// A configuration with a known form factor.
#[derive(Clone, Debug)]
pub struct Config {
    /// Short name (file names, CSV).
    pub name: &'static str,
    /// What it is and where the exact value comes from.
    pub about: &'static str,
    /// The scene; face `i` and face `j` are the pair studied.
    pub scene: Scene,
    /// Emitting face.
    pub i: usize,
    /// Receiving face.
    pub j: usize,
    /// Exact `F_ij`.
    pub exact: f64,
    /// True when no other face blocks any segment between i and j.
    pub unoccluded: bool,
}

/// `Q = Σ` over the four end-point differences of `phi` (see the module docs).
fn along_line(phi: &dyn Fn(f64) -> f64, a: [f64; 2], b: [f64; 2]) -> f64 {
    phi(a[1] - b[0]) + phi(a[0] - b[1]) - phi(a[1] - b[1]) - phi(a[0] - b[0])
}

/// `A_1 F_12` between parallel rectangles `a = [x1, x2] x [y1, y2]` and `b` (same axes) in
/// parallel planes a distance `h` apart, facing each other (superposition of Howell C-11).
pub fn parallel_offset(a: [[f64; 2]; 2], b: [[f64; 2]; 2], h: f64) -> f64 {
    let phi = |x: f64, y: f64| {
        let (x, y) = (x.abs(), y.abs());
        if x == 0.0 || y == 0.0 {
            0.0
        } else {
            x * y * parallel_rectangles(x, y, h) / 4.0
        }
    };
    let mut q = 0.0;
    for (xi, &ax) in a[0].iter().enumerate() {
        for (xk, &bx) in b[0].iter().enumerate() {
            let sx = if xi != xk { 1.0 } else { -1.0 };
            for (yj, &ay) in a[1].iter().enumerate() {
                for (yl, &by) in b[1].iter().enumerate() {
                    let sy = if yj != yl { 1.0 } else { -1.0 };
                    q += sx * sy * phi(ax - bx, ay - by);
                }
            }
        }
    }
    q
}

/// `A_1 F_12` from the rectangle of width `w` spanning `a` along the common line of two
/// perpendicular planes to the rectangle of height `h` spanning `b` along it (superposition
/// of Howell C-14).
pub fn perpendicular_offset(w: f64, h: f64, a: [f64; 2], b: [f64; 2]) -> f64 {
    let phi = |x: f64| {
        let x = x.abs();
        if x == 0.0 {
            0.0
        } else {
            w * x * perpendicular_rectangles(h, x, w) / 2.0
        }
    };
    along_line(&phi, a, b)
}

/// A scene from quads given as `(origin, e1, e2)`: corners `o, o+e1, o+e1+e2, o+e2`, front
/// side along `e1 x e2`.
fn scene(name: &str, quads: &[(DVec3, DVec3, DVec3)]) -> Scene {
    let mut positions = Vec::new();
    let mut faces = Vec::new();
    for &(o, e1, e2) in quads {
        let k = positions.len() as u32;
        positions.extend([o, o + e1, o + e1 + e2, o + e2]);
        faces.push(Face::new(
            [k, k + 1, k + 2, k + 3],
            0,
            faces.len() as u32,
            0,
        ));
    }
    let faces_len = faces.len();
    Scene {
        name: name.to_string(),
        source: format!("study:{name}"),
        positions,
        faces,
        uvs: Vec::new(),
        materials: vec![Material {
            name: "white".into(),
            rho: [0.5; 3],
            emit: [1.0; 3],
            thermal: None,
            two_sided: false,
        }],
        objects: (0..faces_len).map(|k| format!("quad{k}")).collect(),
        units: None,
        camera: None,
        warnings: Vec::new(),
    }
}

fn v(x: f64, y: f64, z: f64) -> DVec3 {
    DVec3::new(x, y, z)
}

/// Length of the shelf of [`all`] (in widths) and the slice studied.
pub const SHELF_LENGTH: f64 = 11.0;

/// All configurations, in the order of the study's tables.
pub fn all() -> Vec<Config> {
    let unit_floor = (v(0., 0., 0.), v(1., 0., 0.), v(0., 1., 0.)); // z = 0, normal +z
    let parallel = |h: f64| {
        scene(
            "parallel",
            &[unit_floor, (v(0., 0., h), v(0., 1., 0.), v(1., 0., 0.))],
        )
    };
    let grazing_h = 0.05;
    let (small, big) = (0.2, 2.0);
    let (z0, len) = (0.5 * (SHELF_LENGTH - 1.0), SHELF_LENGTH);
    let shelf_b = 1.0;
    vec![
        Config {
            name: "adjacent",
            about: "unit squares at 90° with a common edge (Howell C-14)",
            // Wall x = 0, normal +x, sharing the edge y in [0, 1] with the floor.
            scene: scene(
                "adjacent",
                &[unit_floor, (v(0., 0., 0.), v(0., 1., 0.), v(0., 0., 1.))],
            ),
            i: 0,
            j: 1,
            exact: perpendicular_rectangles(1.0, 1.0, 1.0),
            unoccluded: true,
        },
        Config {
            name: "near",
            about: "opposed unit squares 0.2 apart (Howell C-11)",
            scene: parallel(0.2),
            i: 0,
            j: 1,
            exact: parallel_rectangles(1.0, 1.0, 0.2),
            unoccluded: true,
        },
        Config {
            name: "far",
            about: "opposed unit squares 5 apart (Howell C-11)",
            scene: parallel(5.0),
            i: 0,
            j: 1,
            exact: parallel_rectangles(1.0, 1.0, 5.0),
            unoccluded: true,
        },
        Config {
            name: "grazing",
            about: "unit square to a 1 x 0.05 strip standing on its edge: every ray leaves \
                    the square within 3° of its plane (Howell C-14, h = 0.05)",
            scene: scene(
                "grazing",
                &[
                    unit_floor,
                    (v(0., 0., 0.), v(0., 1., 0.), v(0., 0., grazing_h)),
                ],
            ),
            i: 0,
            j: 1,
            exact: perpendicular_rectangles(grazing_h, 1.0, 1.0),
            unoccluded: true,
        },
        Config {
            name: "small-large",
            about: "0.2 x 0.2 square facing the centre of a 2 x 2 square 1 away \
                    (C-11 superposition)",
            scene: scene(
                "small-large",
                &[
                    (v(-0.1, -0.1, 0.), v(small, 0., 0.), v(0., small, 0.)),
                    (v(-1., -1., 1.), v(0., big, 0.), v(big, 0., 0.)),
                ],
            ),
            i: 0,
            j: 1,
            exact: parallel_offset([[-0.1, 0.1], [-0.1, 0.1]], [[-1., 1.], [-1., 1.]], 1.0)
                / (small * small),
            unoccluded: true,
        },
        Config {
            name: "occluded",
            about: "opposed unit squares 1 apart split by a perpendicular divider at x = 0.5: \
                    each half sees only the opposite half, F = F_C-11(0.5, 1, 1)",
            scene: scene(
                "occluded",
                &[
                    unit_floor,
                    (v(0., 0., 1.), v(0., 1., 0.), v(1., 0., 0.)),
                    (v(0.5, 0., 0.), v(0., 1., 0.), v(0., 0., 1.)),
                ],
            ),
            i: 0,
            j: 1,
            exact: parallel_rectangles(0.5, 1.0, 1.0),
            unoccluded: false,
        },
        Config {
            name: "shelf",
            about: "middle unit slice of the floor of an 11-long shelf (floor, back wall and \
                    top of width 1) to the whole back wall (C-14 superposition; the 2D \
                    crossed-strings value is (2 - √2)/2)",
            // Floor slice y = 0, z in [z0, z0 + 1], normal +y; wall x = 0, normal +x;
            // top y = 1, normal -y.
            scene: scene(
                "shelf",
                &[
                    (v(0., 0., z0), v(0., 0., 1.), v(1., 0., 0.)),
                    (v(0., 0., 0.), v(0., shelf_b, 0.), v(0., 0., len)),
                    (v(0., shelf_b, 0.), v(1., 0., 0.), v(0., 0., len)),
                ],
            ),
            i: 0,
            j: 1,
            exact: perpendicular_offset(1.0, shelf_b, [z0, z0 + 1.0], [0.0, len]),
            unoccluded: true,
        },
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analytic::{gauss_legendre, point_to_polygon, shelf_factors};
    use crate::mesh::{PatchSet, Resolution};

    /// `F_ij` by a tensor Gauss rule of the exact point-to-polygon factor over face i.
    fn quadrature(s: &Scene, i: usize, j: usize, order: usize) -> f64 {
        let c = |f: usize| -> Vec<DVec3> {
            s.faces[f]
                .corner_slice()
                .iter()
                .map(|&k| s.positions[k as usize])
                .collect()
        };
        let (a, b) = (c(i), c(j));
        let (e1, e2) = (a[1] - a[0], a[3] - a[0]);
        let n = e1.cross(e2).normalize();
        let area = e1.cross(e2).length();
        let rule = gauss_legendre(order);
        let mut sum = 0.0;
        for &(u, wu) in &rule {
            for &(w, ww) in &rule {
                sum += wu * ww * point_to_polygon(a[0] + e1 * u + e2 * w, n, &b);
            }
        }
        sum * area / area
    }

    #[test]
    fn closed_forms_match_quadrature_and_normals_face_each_other() {
        for c in all() {
            let p = PatchSet::build(&c.scene, Resolution::MaxEdge(100.0)).unwrap();
            assert_eq!(p.len(), c.scene.faces.len(), "{}", c.name);
            let d = p.centroid[c.j] - p.centroid[c.i];
            assert!(
                p.normal[c.i].dot(d) > 0.0 && p.normal[c.j].dot(d) < 0.0,
                "{}",
                c.name
            );
            if c.unoccluded {
                let q = quadrature(&c.scene, c.i, c.j, 64);
                assert!(
                    (q - c.exact).abs() < 1e-6 * c.exact,
                    "{}: closed form {} vs quadrature {q}",
                    c.name,
                    c.exact
                );
            }
        }
    }

    #[test]
    fn shelf_slice_tends_to_the_crossed_strings_value() {
        let two_d = shelf_factors(1.0).0;
        let slice =
            |l: f64| perpendicular_offset(1.0, 1.0, [0.5 * (l - 1.0), 0.5 * (l + 1.0)], [0.0, l]);
        let (e11, e101) = (slice(11.0) - two_d, slice(101.0) - two_d);
        assert!(e11 < 0.0 && e11.abs() < 2e-3, "{e11}");
        assert!(e101.abs() < e11.abs() / 100.0, "{e101}");
    }

    #[test]
    fn occluded_value_is_the_sum_of_the_halves() {
        // Each half pair by the offset rule equals the C-11 value of a half pair.
        let half = parallel_offset([[0., 0.5], [0., 1.]], [[0., 0.5], [0., 1.]], 1.0);
        assert!((half - 0.5 * parallel_rectangles(0.5, 1.0, 1.0)).abs() < 1e-12);
        let cross = parallel_offset([[0., 0.5], [0., 1.]], [[0.5, 1.], [0., 1.]], 1.0);
        let whole = parallel_rectangles(1.0, 1.0, 1.0);
        assert!((2.0 * half + 2.0 * cross - whole).abs() < 1e-12);
    }
}
