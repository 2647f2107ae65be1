//! The suite's catalogue: every case with its exact value and where that value comes from.
//!
//! Exact values are never re-derived here: they come from the closed forms of
//! [`crate::analytic`] (Howell C-11, C-14), the superposition rules of
//! [`crate::study::configs`] (offset rectangles, built on C-11 and C-14), and three
//! arguments that need no formula:
//!
//! - **Additivity over the receiver** (Siegel and Howell, "configuration-factor algebra"):
//!   `F_A,B∪C = F_AB + F_AC` for disjoint `B`, `C`; a receiver with a hole is the outer
//!   shape minus the hole, a wall lifted by a gap `g` is the wall from 0 to `1 + g` minus
//!   the strip from 0 to `g`.
//! - **Closure and symmetry in a closed convex enclosure**: the rows of a closed
//!   enclosure sum to 1, a planar face sees none of itself, and faces that a symmetry of
//!   the enclosure maps onto each other receive equal shares. A regular pyramid's base
//!   sees each of its `n` sides with `F = 1/n`; a regular tetrahedron's face sees each
//!   other face with `F = 1/3`.
//! - **Blocking by a divider**: a wall standing on the whole width of a floor, up to a
//!   ceiling of the same extent, meets every segment between the floor on one side and
//!   the ceiling on the other (the segment's point at the wall's plane lies between the
//!   segment's ends, so inside the wall). Each side then sees only its own side.
//!
//! Rigidly moved and scaled copies keep the exact value of the case they copy. The
//! study's configurations ([`crate::study::configs::all`]) are included as they are.

use std::f64::consts::PI;

use glam::{DMat3, DVec3};

use super::{polygon_area, Case, Class, Surface};
use crate::analytic::{parallel_rectangles, perpendicular_rectangles};
use crate::study::configs::{self, parallel_offset, perpendicular_offset};

fn v(x: f64, y: f64, z: f64) -> DVec3 {
    DVec3::new(x, y, z)
}

/// The parallelogram `o, o + e1, o + e1 + e2, o + e2`: front side along `e1 x e2`.
fn quad(o: DVec3, e1: DVec3, e2: DVec3) -> Vec<DVec3> {
    vec![o, o + e1, o + e1 + e2, o + e2]
}

/// `p` reversed if needed so that its front faces the point `toward`.
fn facing(mut p: Vec<DVec3>, toward: DVec3) -> Vec<DVec3> {
    let n = crate::scene::polygon::newell(&p);
    let c = p.iter().copied().sum::<DVec3>() / p.len() as f64;
    if n.dot(toward - c) < 0.0 {
        p.reverse();
    }
    p
}

fn surface(name: &str, polygons: Vec<Vec<DVec3>>) -> Surface {
    Surface {
        name: name.to_string(),
        polygons,
    }
}

/// A case with no blocking between the pair.
#[allow(clippy::too_many_arguments)]
fn case(
    name: &str,
    class: Class,
    about: &str,
    surfaces: Vec<Surface>,
    from: usize,
    to: usize,
    exact: f64,
    source: &str,
) -> Case {
    Case {
        name: name.to_string(),
        class,
        about: about.to_string(),
        surfaces,
        from,
        to,
        exact,
        source: source.to_string(),
        visible: Vec::new(),
    }
}

/// Floor `[x0, x0 + a] x [y0, y0 + b]` at `z = 0` facing up.
fn floor(x0: f64, y0: f64, a: f64, b: f64) -> Vec<DVec3> {
    quad(v(x0, y0, 0.0), v(a, 0.0, 0.0), v(0.0, b, 0.0))
}

/// Ceiling `[x0, x0 + a] x [y0, y0 + b]` at `z = h` facing down.
fn ceiling(x0: f64, y0: f64, a: f64, b: f64, h: f64) -> Vec<DVec3> {
    quad(v(x0, y0, h), v(0.0, b, 0.0), v(a, 0.0, 0.0))
}

/// Wall in the plane `x = 0`, `y` in `[y0, y0 + l]`, `z` in `[z0, z0 + h]`, facing `+x`.
fn wall(y0: f64, l: f64, z0: f64, h: f64) -> Vec<DVec3> {
    quad(v(0.0, y0, z0), v(0.0, l, 0.0), v(0.0, 0.0, h))
}

/// Howell C-11: rectangles `a x b` a distance `c` apart, surfaces `A` (floor) and `B`.
fn c11(name: &str, class: Class, about: &str, a: f64, b: f64, c: f64) -> Case {
    case(
        name,
        class,
        about,
        vec![
            surface("A", vec![floor(0.0, 0.0, a, b)]),
            surface("B", vec![ceiling(0.0, 0.0, a, b, c)]),
        ],
        0,
        1,
        parallel_rectangles(a, b, c),
        &format!("Howell C-11, a = {a}, b = {b}, c = {c}"),
    )
}

/// Howell C-14: from the floor `w x l` to the wall `h x l` on the common edge of length `l`.
fn c14(name: &str, class: Class, about: &str, h: f64, l: f64, w: f64) -> Case {
    case(
        name,
        class,
        about,
        vec![
            surface("A", vec![floor(0.0, 0.0, w, l)]),
            surface("B", vec![wall(0.0, l, 0.0, h)]),
        ],
        0,
        1,
        perpendicular_rectangles(h, l, w),
        &format!("Howell C-14, h = {h}, l = {l}, w = {w}"),
    )
}

/// Parallel offset rectangles: floor `a` at `z = 0` to ceiling `b` at `z = h`.
fn offset(
    name: &str,
    class: Class,
    about: &str,
    a: [[f64; 2]; 2],
    b: [[f64; 2]; 2],
    h: f64,
) -> Case {
    let area = (a[0][1] - a[0][0]) * (a[1][1] - a[1][0]);
    case(
        name,
        class,
        about,
        vec![
            surface(
                "A",
                vec![floor(
                    a[0][0],
                    a[1][0],
                    a[0][1] - a[0][0],
                    a[1][1] - a[1][0],
                )],
            ),
            surface(
                "B",
                vec![ceiling(
                    b[0][0],
                    b[1][0],
                    b[0][1] - b[0][0],
                    b[1][1] - b[1][0],
                    h,
                )],
            ),
        ],
        0,
        1,
        parallel_offset(a, b, h) / area,
        &format!("C-11 superposition (parallel offset), A = {a:?}, B = {b:?}, h = {h}"),
    )
}

/// Perpendicular rectangles offset along their common line: the floor of width `w`
/// spanning `a` along `y` to the wall of height `h` spanning `b`.
fn perp_offset(
    name: &str,
    class: Class,
    about: &str,
    w: f64,
    h: f64,
    a: [f64; 2],
    b: [f64; 2],
) -> Case {
    case(
        name,
        class,
        about,
        vec![
            surface("A", vec![floor(0.0, a[0], w, a[1] - a[0])]),
            surface("B", vec![wall(b[0], b[1] - b[0], 0.0, h)]),
        ],
        0,
        1,
        perpendicular_offset(w, h, a, b) / (w * (a[1] - a[0])),
        &format!("C-14 superposition along the common line, w = {w}, h = {h}, A spans {a:?}, B spans {b:?}"),
    )
}

/// A regular pyramid of `n` sides over a base of circumradius 1 at `z = 0`, apex at
/// height `height`: the base (as `n` triangles from the centre, or one square when
/// `n == 4`) and its sides, all facing in. From the base to side 0: `1/n`.
fn pyramid(name: &str, about: &str, n: usize, height: f64) -> Case {
    let apex = v(0.0, 0.0, height);
    let inside = v(0.0, 0.0, height / 4.0);
    let corner = |k: usize| {
        let t = 2.0 * PI * k as f64 / n as f64 + PI / n as f64;
        v(t.cos(), t.sin(), 0.0)
    };
    let base = if n == 4 {
        vec![facing((0..4).map(corner).collect(), inside)]
    } else {
        (0..n)
            .map(|k| facing(vec![DVec3::ZERO, corner(k), corner(k + 1)], inside))
            .collect()
    };
    let mut surfaces = vec![surface("base", base)];
    for k in 0..n {
        surfaces.push(surface(
            &format!("side{k}"),
            vec![facing(vec![corner(k), corner(k + 1), apex], inside)],
        ));
    }
    // Dihedral angle between base and side: atan(height / inradius).
    let inradius = (PI / n as f64).cos();
    let angle = (height / inradius).atan().to_degrees();
    case(
        name,
        Class::Touching,
        &format!("{about}; base and side meet at {angle:.1}°"),
        surfaces,
        0,
        1,
        1.0 / n as f64,
        &format!(
            "closure and {n}-fold symmetry of a closed regular pyramid: F(base -> side) = 1/{n}"
        ),
    )
}

/// The regular tetrahedron with corners `(±1, ±1, ±1)` of even parity, faces facing in.
fn tetrahedron_faces() -> Vec<Vec<DVec3>> {
    let p = [
        v(1., 1., 1.),
        v(1., -1., -1.),
        v(-1., 1., -1.),
        v(-1., -1., 1.),
    ];
    (0..4)
        .map(|skip| {
            let tri: Vec<DVec3> = (0..4).filter(|&k| k != skip).map(|k| p[k]).collect();
            facing(tri, DVec3::ZERO)
        })
        .collect()
}

/// The closed box `[0, a] x [0, b] x [0, c]`, faces facing in: floor, ceiling, x = 0,
/// x = a, y = 0, y = b.
fn box_faces(a: f64, b: f64, c: f64) -> Vec<(&'static str, Vec<DVec3>)> {
    let inside = v(a / 2.0, b / 2.0, c / 2.0);
    let (x, y, z) = (v(a, 0., 0.), v(0., b, 0.), v(0., 0., c));
    vec![
        ("floor", facing(quad(DVec3::ZERO, x, y), inside)),
        ("ceiling", facing(quad(z, x, y), inside)),
        ("x0", facing(quad(DVec3::ZERO, y, z), inside)),
        ("x1", facing(quad(x, y, z), inside)),
        ("y0", facing(quad(DVec3::ZERO, x, z), inside)),
        ("y1", facing(quad(y, x, z), inside)),
    ]
}

/// A box case: from face `from` to face `to` (names of [`box_faces`]).
fn box_case(
    name: &str,
    about: &str,
    dims: [f64; 3],
    from: &str,
    to: &str,
    exact: f64,
    source: &str,
) -> Case {
    let faces = box_faces(dims[0], dims[1], dims[2]);
    let find = |n: &str| faces.iter().position(|f| f.0 == n).unwrap();
    let (i, j) = (find(from), find(to));
    case(
        name,
        Class::Enclosure,
        about,
        faces
            .into_iter()
            .map(|(n, p)| surface(n, vec![p]))
            .collect(),
        i,
        j,
        exact,
        source,
    )
}

/// Applies `f` to every point of the case (surfaces and visible pairs).
fn map_points(c: &mut Case, f: &dyn Fn(DVec3) -> DVec3) {
    for s in &mut c.surfaces {
        for p in &mut s.polygons {
            for x in p.iter_mut() {
                *x = f(*x);
            }
        }
    }
    for (p, q) in &mut c.visible {
        for x in p.iter_mut().chain(q.iter_mut()) {
            *x = f(*x);
        }
    }
}

/// A copy of `c` rotated by `angle_deg` about `axis` and moved by `shift`.
fn moved(mut c: Case, name: &str, axis: DVec3, angle_deg: f64, shift: DVec3) -> Case {
    let r = DMat3::from_axis_angle(axis.normalize(), angle_deg.to_radians());
    map_points(&mut c, &|x| r * x + shift);
    c.about = format!(
        "{} (copy of `{}` rotated {angle_deg}° about {axis} and moved by {shift})",
        c.about, c.name
    );
    c.source = format!("{} (invariant under rigid motion)", c.source);
    c.name = name.to_string();
    c.class = Class::RigidMotion;
    c
}

/// A copy of `c` scaled by `k` about the origin.
fn scaled(mut c: Case, name: &str, k: f64) -> Case {
    map_points(&mut c, &|x| x * k);
    c.about = format!("{} (copy of `{}` scaled by {k:e})", c.about, c.name);
    c.source = format!("{} (invariant under scaling)", c.source);
    c.name = name.to_string();
    c.class = Class::Scale;
    c
}

/// The study's configurations, as cases: face i is `A`, face j is `B`, other faces are
/// named `other1`, `other2`, ...
fn study_cases() -> Vec<Case> {
    let mut out = Vec::new();
    for c in configs::all() {
        let s = &c.scene;
        let poly = |f: usize| -> Vec<DVec3> {
            s.faces[f]
                .corner_slice()
                .iter()
                .map(|&k| s.positions[k as usize])
                .collect()
        };
        let mut surfaces = vec![surface("A", vec![poly(c.i)]), surface("B", vec![poly(c.j)])];
        let mut other = 0;
        for f in 0..s.faces.len() {
            if f != c.i && f != c.j {
                other += 1;
                surfaces.push(surface(&format!("other{other}"), vec![poly(f)]));
            }
        }
        let class = match c.name {
            "adjacent" | "shelf" => Class::SharedEdge,
            "near" | "small-large" => Class::Near,
            "far" => Class::Far,
            "grazing" => Class::Grazing,
            _ => Class::Occluded,
        };
        let mut k = case(
            &format!("study-{}", c.name),
            class,
            c.about,
            surfaces,
            0,
            1,
            c.exact,
            &format!(
                "the estimator study's configuration `{}`: {}",
                c.name, c.about
            ),
        );
        if !c.unoccluded {
            // The study's only occluded configuration: unit floor and ceiling 1 apart,
            // divider at x = 0.5 (see `divider`): each half sees only its own half.
            assert_eq!(
                c.name, "occluded",
                "an occluded study configuration with no plan"
            );
            k.visible = vec![
                (floor(0.0, 0.0, 0.5, 1.0), ceiling(0.0, 0.0, 0.5, 1.0, 1.0)),
                (floor(0.5, 0.0, 0.5, 1.0), ceiling(0.5, 0.0, 0.5, 1.0, 1.0)),
            ];
        }
        out.push(k);
    }
    out
}

/// Unit floor and a ceiling at height `h` (the pair), divided by walls at `x = cx` for
/// each `cx` in `xs` and at `y = cy` for each `cy` in `ys`, full height, across the whole
/// width. Returns the case with its visible cells.
fn divided(name: &str, about: &str, h: f64, xs: &[f64], ys: &[f64]) -> Case {
    let cuts = |inner: &[f64]| {
        let mut c = vec![0.0];
        c.extend_from_slice(inner);
        c.push(1.0);
        c
    };
    let (bx, by) = (cuts(xs), cuts(ys));
    let mut dividers = Vec::new();
    let mut visible = Vec::new();
    let mut exact = 0.0;
    let mut parts = Vec::new();
    for wx in bx.windows(2) {
        for wy in by.windows(2) {
            let (a, b) = (wx[1] - wx[0], wy[1] - wy[0]);
            visible.push((floor(wx[0], wy[0], a, b), ceiling(wx[0], wy[0], a, b, h)));
            exact += a * b * parallel_rectangles(a, b, h);
            parts.push(format!("{a} x {b}"));
        }
    }
    // Divider pieces between consecutive cuts of the other direction, so that crossing
    // dividers meet along lines instead of passing through each other.
    for &cx in xs {
        for wy in by.windows(2) {
            dividers.push(quad(
                v(cx, wy[0], 0.0),
                v(0.0, wy[1] - wy[0], 0.0),
                v(0.0, 0.0, h),
            ));
        }
    }
    for &cy in ys {
        for wx in bx.windows(2) {
            dividers.push(quad(
                v(wx[0], cy, 0.0),
                v(0.0, 0.0, h),
                v(wx[1] - wx[0], 0.0, 0.0),
            ));
        }
    }
    let mut c = case(
        name,
        Class::Occluded,
        about,
        vec![
            surface("A", vec![floor(0.0, 0.0, 1.0, 1.0)]),
            surface("B", vec![ceiling(0.0, 0.0, 1.0, 1.0, h)]),
            surface("divider", dividers),
        ],
        0,
        1,
        exact,
        &format!(
            "blocking by full dividers: each cell sees only its own cell, \
             F = Σ A_cell F_C-11(cell, h = {h}) with cells {}",
            parts.join(", ")
        ),
    );
    c.visible = visible;
    c
}

/// The unit cube divided at `x = 0.5` by a wall facing `-x` (toward the wall `x0`).
fn divided_cube(name: &str, about: &str, to: &str) -> Case {
    let mut surfaces: Vec<Surface> = box_faces(1.0, 1.0, 1.0)
        .into_iter()
        .map(|(n, p)| surface(n, vec![p]))
        .collect();
    surfaces.push(surface(
        "divider",
        vec![quad(v(0.5, 0.0, 0.0), v(0.0, 0.0, 1.0), v(0.0, 1.0, 0.0))],
    ));
    let j = surfaces.iter().position(|s| s.name == to).unwrap();
    let left = floor(0.0, 0.0, 0.5, 1.0);
    let target = surfaces[j].polygons[0].clone();
    let mut c = case(
        name,
        Class::Occluded,
        about,
        surfaces,
        0,
        j,
        0.5 * perpendicular_rectangles(1.0, 1.0, 0.5),
        &format!(
            "blocking by the divider: only the floor's half x < 0.5 sees `{to}`, \
             F = 1/2 F_C-14(h = 1, l = 1, w = 0.5)"
        ),
    );
    c.visible = vec![(left, target)];
    c
}

/// Every case of the suite, in table order.
pub fn all() -> Vec<Case> {
    let s3 = 3f64.sqrt();
    let mut out = study_cases();

    // Far.
    out.push(c11(
        "c11-far20",
        Class::Far,
        "opposed unit squares 20 apart",
        1.0,
        1.0,
        20.0,
    ));
    out.push(c11(
        "c11-far-rect",
        Class::Far,
        "opposed 2 x 0.5 rectangles 4 apart",
        2.0,
        0.5,
        4.0,
    ));
    out.push(offset(
        "offset-far",
        Class::Far,
        "unit squares 3 apart, offset by (2, 1)",
        [[0., 1.], [0., 1.]],
        [[2., 3.], [1., 2.]],
        3.0,
    ));

    // Near.
    out.push(c11(
        "c11-near005",
        Class::Near,
        "opposed unit squares 0.05 apart",
        1.0,
        1.0,
        0.05,
    ));
    out.push(c11(
        "c11-near-rect",
        Class::Near,
        "opposed 3 x 0.5 rectangles 0.1 apart",
        3.0,
        0.5,
        0.1,
    ));
    out.push(offset(
        "offset-near-half",
        Class::Near,
        "unit squares 0.25 apart, the receiver shifted by half its width",
        [[0., 1.], [0., 1.]],
        [[0.5, 1.5], [0., 1.]],
        0.25,
    ));

    // The notes' shelf (g = sqrt 3), 11 long: floor slice, back wall slice, top.
    let (len, z0) = (11.0, 5.0);
    let shelf = |from_wall: bool| -> Vec<Surface> {
        let mut s = vec![
            surface("floor-slice", vec![floor(0.0, z0, 1.0, 1.0)]),
            surface(
                "floor-rest",
                vec![
                    floor(0.0, 0.0, 1.0, z0),
                    floor(0.0, z0 + 1.0, 1.0, len - z0 - 1.0),
                ],
            ),
        ];
        if from_wall {
            s.push(surface("wall-slice", vec![wall(z0, 1.0, 0.0, s3)]));
            s.push(surface(
                "wall-rest",
                vec![
                    wall(0.0, z0, 0.0, s3),
                    wall(z0 + 1.0, len - z0 - 1.0, 0.0, s3),
                ],
            ));
        } else {
            s.push(surface("wall", vec![wall(0.0, len, 0.0, s3)]));
        }
        s.push(surface("top", vec![ceiling(0.0, 0.0, 1.0, len, s3)]));
        s
    };
    out.push(case(
        "shelf-floor-wall",
        Class::SharedEdge,
        "the notes' shelf (back wall sqrt 3 times the floor's width), 11 long: middle unit \
         slice of the floor to the whole back wall (2D value: F_AB = (1 + g - sqrt(1 + g²))/2)",
        shelf(false),
        0,
        2,
        perpendicular_offset(1.0, s3, [z0, z0 + 1.0], [0.0, len]),
        "C-14 superposition along the common line, w = 1, h = sqrt 3, slice [5, 6] of [0, 11]",
    ));
    out.push(case(
        "shelf-floor-top",
        Class::Near,
        "the notes' shelf, 11 long: middle unit slice of the floor to the whole top \
         (2D value: F_AC = sqrt(1 + g²) - g)",
        shelf(false),
        0,
        3,
        parallel_offset([[0., 1.], [z0, z0 + 1.0]], [[0., 1.], [0., len]], s3),
        "C-11 superposition (parallel offset), slice [0, 1] x [5, 6], top [0, 1] x [0, 11], h = sqrt 3",
    ));
    {
        // Wall slice to top: the top is the plane z = sqrt 3, meeting the wall along the
        // line x = 0, z = sqrt 3; the wall is the emitter of width sqrt 3 from that line.
        let area = s3;
        out.push(case(
            "shelf-wall-top",
            Class::SharedEdge,
            "the notes' shelf, 11 long: middle unit slice of the back wall to the whole top \
             (2D value: F_BC = (1 + 1/g - sqrt(1 + 1/g²))/2)",
            shelf(true),
            2,
            4,
            perpendicular_offset(s3, 1.0, [z0, z0 + 1.0], [0.0, len]) / area,
            "C-14 superposition along the common line, w = sqrt 3, h = 1, slice [5, 6] of [0, 11]",
        ));
    }

    // Sharing an edge at 90°.
    out.push(c14(
        "c14-tall",
        Class::SharedEdge,
        "floor 0.5 x 1 to a wall 2 high on the common edge of 1",
        2.0,
        1.0,
        0.5,
    ));
    out.push(c14(
        "c14-long",
        Class::SharedEdge,
        "floor 1.7 x 2 to a wall 0.3 high on the common edge of 2",
        0.3,
        2.0,
        1.7,
    ));
    out.push(perp_offset(
        "c14-half-edge",
        Class::SharedEdge,
        "unit floor and unit wall at 90° sharing half of an edge",
        1.0,
        1.0,
        [0.0, 1.0],
        [0.5, 1.5],
    ));

    // Touching at an angle.
    out.push(perp_offset(
        "c14-corner",
        Class::Touching,
        "unit floor and unit wall at 90° touching at one corner point only",
        1.0,
        1.0,
        [0.0, 1.0],
        [1.0, 2.0],
    ));
    out.push(pyramid(
        "pyramid4-flat",
        "closed square pyramid, base diagonal 2, height 0.2",
        4,
        0.2,
    ));
    out.push(pyramid(
        "pyramid4",
        "closed square pyramid, base diagonal 2, height 1",
        4,
        1.0,
    ));
    out.push(pyramid(
        "pyramid4-steep",
        "closed square pyramid, base diagonal 2, height 4",
        4,
        4.0,
    ));
    out.push(pyramid(
        "pyramid6",
        "closed hexagonal pyramid, base of circumradius 1 as 6 triangles, height 1",
        6,
        1.0,
    ));
    {
        let faces = tetrahedron_faces();
        let surfaces = faces
            .into_iter()
            .enumerate()
            .map(|(k, p)| surface(&format!("face{k}"), vec![p]))
            .collect();
        out.push(case(
            "tetrahedron",
            Class::Touching,
            "closed regular tetrahedron: one face to another (they meet at 70.5°)",
            surfaces,
            0,
            1,
            1.0 / 3.0,
            "closure and symmetry of a closed regular tetrahedron: F = 1/3",
        ));
    }

    // Thin gaps.
    out.push(c11(
        "c11-gap1e-3",
        Class::ThinGap,
        "opposed unit squares 0.001 apart",
        1.0,
        1.0,
        1e-3,
    ));
    out.push(c11(
        "c11-gap-rect",
        Class::ThinGap,
        "opposed 2 x 1 rectangles 0.01 apart",
        2.0,
        1.0,
        0.01,
    ));
    {
        let mut c = offset(
            "offset-gap-half",
            Class::ThinGap,
            "unit squares 0.01 apart, the receiver shifted by half its width (its edge \
             hangs 0.01 above the middle of the emitter)",
            [[0., 1.], [0., 1.]],
            [[0.5, 1.5], [0., 1.]],
            0.01,
        );
        // For the quadrature: the emitter split under the receiver's edge.
        let b = c.surfaces[1].polygons[0].clone();
        c.visible = vec![
            (floor(0.0, 0.0, 0.5, 1.0), b.clone()),
            (floor(0.5, 0.0, 0.5, 1.0), b),
        ];
        out.push(c);
    }
    {
        let g = 1e-3;
        out.push(case(
            "c14-lifted",
            Class::ThinGap,
            "unit floor to a unit wall at 90° lifted 0.001 above the floor's edge",
            vec![
                surface("A", vec![floor(0.0, 0.0, 1.0, 1.0)]),
                surface("B", vec![wall(0.0, 1.0, g, 1.0)]),
            ],
            0,
            1,
            perpendicular_rectangles(1.0 + g, 1.0, 1.0) - perpendicular_rectangles(g, 1.0, 1.0),
            "additivity: F_C-14(h = 1.001, l = 1, w = 1) - F_C-14(h = 0.001, l = 1, w = 1)",
        ));
    }

    // Grazing.
    out.push(c14(
        "c14-grazing",
        Class::Grazing,
        "unit floor to a 1 x 0.005 strip standing on its edge",
        0.005,
        1.0,
        1.0,
    ));
    out.push(offset(
        "offset-grazing",
        Class::Grazing,
        "unit squares 0.1 apart, the receiver 3 widths to the side",
        [[0., 1.], [0., 1.]],
        [[3., 4.], [0., 1.]],
        0.1,
    ));
    out.push(perp_offset(
        "c14-grazing-far",
        Class::Grazing,
        "unit floor to a 1 x 0.05 strip at 90°, one width further along the common line",
        1.0,
        0.05,
        [0.0, 1.0],
        [2.0, 3.0],
    ));

    // Occluded.
    out.push(divided(
        "divider-03",
        "unit floor and ceiling 0.5 apart, a full divider at x = 0.3",
        0.5,
        &[0.3],
        &[],
    ));
    out.push(divided(
        "divider-cross",
        "unit floor and ceiling 1 apart, full dividers at x = 0.5 and y = 0.5",
        1.0,
        &[0.5],
        &[0.5],
    ));
    out.push(divided_cube(
        "cube-divided-wall",
        "closed unit cube divided at x = 0.5 by a one-sided wall facing x = 0: floor to the wall x = 0",
        "x0",
    ));
    out.push(divided_cube(
        "cube-divided-divider",
        "closed unit cube divided at x = 0.5 by a one-sided wall facing x = 0: floor to the divider",
        "divider",
    ));

    // Holes.
    {
        let small = floor(-0.1, -0.1, 0.2, 0.2);
        let frame = vec![
            ceiling(-1.0, -1.0, 2.0, 0.5, 1.0),
            ceiling(-1.0, 0.5, 2.0, 0.5, 1.0),
            ceiling(-1.0, -0.5, 0.5, 1.0, 1.0),
            ceiling(0.5, -0.5, 0.5, 1.0, 1.0),
        ];
        let a = [[-0.1, 0.1], [-0.1, 0.1]];
        let exact = (parallel_offset(a, [[-1., 1.], [-1., 1.]], 1.0)
            - parallel_offset(a, [[-0.5, 0.5], [-0.5, 0.5]], 1.0))
            / 0.04;
        out.push(case(
            "frame-receiver",
            Class::Hole,
            "a 0.2 x 0.2 square to a 2 x 2 frame with a 1 x 1 hole centred above it, 1 away",
            vec![surface("A", vec![small]), surface("B", frame.clone())],
            0,
            1,
            exact,
            "additivity: C-11 superposition to the 2 x 2 square minus to the 1 x 1 hole",
        ));
        let emitter: Vec<Vec<DVec3>> = frame
            .iter()
            .map(|p| {
                let mut q: Vec<DVec3> = p.iter().map(|x| v(x.x, x.y, 0.0)).collect();
                q.reverse();
                q
            })
            .collect();
        let sq = [[-1.0, 1.0], [-1.0, 1.0]];
        let exact = (parallel_offset(sq, sq, 0.5)
            - parallel_offset([[-0.5, 0.5], [-0.5, 0.5]], sq, 0.5))
            / 3.0;
        out.push(case(
            "frame-emitter",
            Class::Hole,
            "a 2 x 2 frame with a 1 x 1 hole to the 2 x 2 square 0.5 above it",
            vec![
                surface("A", emitter),
                surface("B", vec![ceiling(-1.0, -1.0, 2.0, 2.0, 0.5)]),
            ],
            0,
            1,
            exact,
            "additivity over the emitter: (4 F_C-11(2, 2, 0.5) - 1 F(hole -> square)) / 3, \
             the hole's factor by C-11 superposition",
        ));
    }

    // Enclosures.
    let cube_rest = {
        let faces = box_faces(1.0, 1.0, 1.0);
        let mut it = faces.into_iter();
        let (_, f) = it.next().unwrap();
        let rest: Vec<Vec<DVec3>> = it.map(|(_, p)| p).collect();
        case(
            "cube-closure",
            Class::Enclosure,
            "closed unit cube: the floor to the other five faces together",
            vec![surface("floor", vec![f]), surface("rest", rest)],
            0,
            1,
            1.0,
            "closure of a closed enclosure: a planar face's row sums to 1",
        )
    };
    out.push(box_case(
        "cube-opposite",
        "closed unit cube: floor to ceiling",
        [1.0, 1.0, 1.0],
        "floor",
        "ceiling",
        parallel_rectangles(1.0, 1.0, 1.0),
        "Howell C-11, a = b = c = 1",
    ));
    out.push(box_case(
        "cube-adjacent",
        "closed unit cube: floor to a wall",
        [1.0, 1.0, 1.0],
        "floor",
        "x0",
        perpendicular_rectangles(1.0, 1.0, 1.0),
        "Howell C-14, h = l = w = 1",
    ));
    out.push(cube_rest);
    out.push(box_case(
        "box-opposite",
        "closed 1 x 2 x 3 box: floor (1 x 2) to ceiling",
        [1.0, 2.0, 3.0],
        "floor",
        "ceiling",
        parallel_rectangles(1.0, 2.0, 3.0),
        "Howell C-11, a = 1, b = 2, c = 3",
    ));
    out.push(box_case(
        "box-wall-x",
        "closed 1 x 2 x 3 box: floor to the 2 x 3 wall x = 0",
        [1.0, 2.0, 3.0],
        "floor",
        "x0",
        perpendicular_rectangles(3.0, 2.0, 1.0),
        "Howell C-14, h = 3, l = 2, w = 1",
    ));
    out.push(box_case(
        "box-wall-y",
        "closed 1 x 2 x 3 box: floor to the 1 x 3 wall y = 0",
        [1.0, 2.0, 3.0],
        "floor",
        "y0",
        perpendicular_rectangles(3.0, 1.0, 2.0),
        "Howell C-14, h = 3, l = 1, w = 2",
    ));
    {
        let faces = tetrahedron_faces();
        let rest = faces[1..].to_vec();
        out.push(case(
            "tetrahedron-closure",
            Class::Enclosure,
            "closed regular tetrahedron: one face to the other three together",
            vec![
                surface("face0", vec![faces[0].clone()]),
                surface("rest", rest),
            ],
            0,
            1,
            1.0,
            "closure of a closed enclosure: a planar face's row sums to 1",
        ));
    }

    // Rigid motions of catalogue cases.
    let find = |out: &[Case], name: &str| out.iter().find(|c| c.name == name).unwrap().clone();
    let axis = v(1.0, 2.0, 3.0);
    let moves = [
        ("study-adjacent", "moved-c14", 37.0, v(3.1, -2.4, 5.7)),
        (
            "c11-near005",
            "moved-c11-near-far-away",
            23.0,
            v(1000.0, 2000.0, -500.0),
        ),
        (
            "study-near",
            "moved-c11-near-very-far",
            71.0,
            v(1e4, -2e4, 5e3),
        ),
        ("study-occluded", "moved-divider", 115.0, v(-7.0, 3.0, 2.0)),
        ("pyramid4", "moved-pyramid4", 200.0, v(0.5, 0.25, -3.0)),
    ];
    for (src, name, angle, shift) in moves {
        let c = find(&out, src);
        out.push(moved(c, name, axis, angle, shift));
    }
    // Scale extremes.
    let unit_c11 = c11(
        "c11-unit",
        Class::Far,
        "opposed unit squares 1 apart",
        1.0,
        1.0,
        1.0,
    );
    out.push(scaled(unit_c11.clone(), "scaled-c11-1e-3", 1e-3));
    out.push(scaled(unit_c11, "scaled-c11-1e3", 1e3));
    let unit_c14 = find(&out, "study-adjacent");
    out.push(scaled(unit_c14.clone(), "scaled-c14-1e-4", 1e-4));
    out.push(scaled(unit_c14, "scaled-c14-1e4", 1e4));
    {
        let mut c = c11(
            "c11-sliver",
            Class::Scale,
            "opposed 10 x 0.01 slivers 1 apart (aspect 1000)",
            10.0,
            0.01,
            1.0,
        );
        c.class = Class::Scale;
        out.push(c);
    }
    out
}

/// Area of the from-surface (the weights of the surface factor).
pub fn from_area(c: &Case) -> f64 {
    c.surfaces[c.from]
        .polygons
        .iter()
        .map(|p| polygon_area(p))
        .sum()
}

#[cfg(test)]
mod tests {
    //! Every exact value recomputed by quadrature of the defining integral
    //! `F = 1/A_A ∫_A ∫_B cos θ_x cos θ_y / (π r²)`, over the visible pairs each case names,
    //! with no closed form involved: the outer integral over the emitter by a tensor
    //! Gauss–Legendre rule graded geometrically toward each edge as far as that edge's
    //! distance to the receiver needs (the point factor has logarithmic singularities
    //! where the surfaces touch), the inner integral over the receiver by
    //! bisecting its triangles' longest edges toward the point until each piece is small
    //! against its distance, then a fixed Gauss rule on each piece.

    use std::collections::BTreeSet;

    use rayon::prelude::*;

    use super::*;
    use crate::analytic::gauss_legendre;

    /// Most panels graded toward one end of a parameter.
    const LEVELS: usize = 10;
    /// Ratio of consecutive graded panels.
    const SIGMA: f64 = 0.2;

    /// `(node, weight)` on `[0, 1]`: 8-point Gauss panels graded geometrically (ratio
    /// [`SIGMA`]) toward 0 with `l0` panels below 1/2 and toward 1 with `l1` above.
    fn graded_ends(l0: usize, l1: usize) -> Vec<(f64, f64)> {
        let gl = gauss_legendre(8);
        let mut cuts = vec![0.0];
        for k in (0..l0).rev() {
            cuts.push(0.5 * SIGMA.powi(k as i32 + 1));
        }
        cuts.push(0.5);
        for k in 0..l1 {
            cuts.push(1.0 - 0.5 * SIGMA.powi(k as i32 + 1));
        }
        cuts.push(1.0);
        let mut out = Vec::new();
        for w in cuts.windows(2) {
            let (a, b) = (w[0], w[1]);
            for &(x, wx) in &gl {
                out.push((a + (b - a) * x, (b - a) * wx));
            }
        }
        out
    }

    fn segment_distance(x: DVec3, a: DVec3, b: DVec3) -> f64 {
        let d = b - a;
        let l2 = d.length_squared();
        let t = if l2 > 0.0 {
            ((x - a).dot(d) / l2).clamp(0.0, 1.0)
        } else {
            0.0
        };
        (a + d * t - x).length()
    }

    /// Distance from `x` to the convex planar polygon `q`.
    fn polygon_distance(x: DVec3, q: &[DVec3]) -> f64 {
        let n = normal(q);
        let h = n.dot(x - q[0]);
        let y = x - n * h;
        let m = q.len();
        let inside = (0..m).all(|k| (q[(k + 1) % m] - q[k]).cross(y - q[k]).dot(n) >= 0.0);
        if inside {
            h.abs()
        } else {
            (0..m)
                .map(|k| segment_distance(x, q[k], q[(k + 1) % m]))
                .fold(f64::INFINITY, f64::min)
        }
    }

    /// Graded panels toward an emitter edge `a b`: enough that the smallest is small
    /// against the edge's distance to the receiver `q` (sampled along the edge).
    fn levels(a: DVec3, b: DVec3, q: &[DVec3], size: f64) -> usize {
        let d = (0..=32)
            .map(|k| polygon_distance(a + (b - a) * (k as f64 / 32.0), q))
            .fold(f64::INFINITY, f64::min);
        if d <= 1e-12 * size {
            return LEVELS;
        }
        let l = ((d / size).ln() / SIGMA.ln()).ceil() + 2.0;
        (l.max(1.0) as usize).min(LEVELS)
    }

    /// Parametrization of a triangle or parallelogram over the unit square: point and
    /// Jacobian (the triangle by the collapsed map `p0 + s (p1 - p0) + s t (p2 - p1)`).
    fn param(p: &[DVec3], s: f64, t: f64) -> (DVec3, f64) {
        if p.len() == 3 {
            let x = p[0] + (p[1] - p[0]) * s + (p[2] - p[1]) * (s * t);
            (x, s * (p[1] - p[0]).cross(p[2] - p[0]).length())
        } else {
            let x = p[0] + (p[1] - p[0]) * s + (p[3] - p[0]) * t;
            (x, (p[1] - p[0]).cross(p[3] - p[0]).length())
        }
    }

    fn normal(p: &[DVec3]) -> DVec3 {
        crate::scene::polygon::newell(p).normalize()
    }

    /// `∫_T cos θ_x cos θ_y / (π r²) dA_y` over the triangle `t` (normal `n_y`) from `x`.
    fn inner(
        x: DVec3,
        n_x: DVec3,
        t: [DVec3; 3],
        n_y: DVec3,
        rule: &[(f64, f64)],
        depth: u32,
    ) -> f64 {
        let c = (t[0] + t[1] + t[2]) / 3.0;
        let radius = t.iter().map(|p| (*p - c).length()).fold(0.0, f64::max);
        // Pieces are split until small against their distance, down to about 2^-32 of
        // the receiver's size, and never below the rounding of the coordinates.
        if (x - c).length() > 3.0 * radius || depth >= 64 || radius < 1e-13 * x.length() {
            let mut sum = 0.0;
            for &(s, ws) in rule {
                for &(u, wu) in rule {
                    let (y, jac) = param(&t, s, u);
                    let d = y - x;
                    let r2 = d.length_squared();
                    let (cx, cy) = (n_x.dot(d), -n_y.dot(d));
                    if cx > 0.0 && cy > 0.0 {
                        sum += ws * wu * jac * cx * cy / (PI * r2 * r2);
                    }
                }
            }
            return sum;
        }
        // Longest-edge bisection keeps the pieces well shaped (no slivers).
        let l = [
            (t[1] - t[0]).length_squared(),
            (t[2] - t[1]).length_squared(),
            (t[0] - t[2]).length_squared(),
        ];
        let k = if l[0] >= l[1] && l[0] >= l[2] {
            0
        } else if l[1] >= l[2] {
            1
        } else {
            2
        };
        let (a, b, c) = (t[k], t[(k + 1) % 3], t[(k + 2) % 3]);
        let m = (a + b) / 2.0;
        inner(x, n_x, [a, m, c], n_y, rule, depth + 1)
            + inner(x, n_x, [m, b, c], n_y, rule, depth + 1)
    }

    /// `A_p F_pq` by quadrature, unblocked.
    fn area_factor(p: &[DVec3], q: &[DVec3]) -> f64 {
        // The emitter's edges at the ends of each parameter (s = 0 of a triangle is its
        // corner p0).
        let (s0, s1, t0, t1) = if p.len() == 3 {
            ((p[0], p[0]), (p[1], p[2]), (p[0], p[1]), (p[0], p[2]))
        } else {
            ((p[0], p[3]), (p[1], p[2]), (p[0], p[1]), (p[3], p[2]))
        };
        let size = (p[1] - p[0]).length().max((p[2] - p[0]).length());
        let l = |e: (DVec3, DVec3)| levels(e.0, e.1, q, size);
        let (rs, rt) = (graded_ends(l(s0), l(s1)), graded_ends(l(t0), l(t1)));
        let rule = gauss_legendre(6);
        let (n_x, n_y) = (normal(p), normal(q));
        let tris: Vec<[DVec3; 3]> = if q.len() == 3 {
            vec![[q[0], q[1], q[2]]]
        } else {
            vec![[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
        };
        let mut sum = 0.0;
        for &(s, ws) in &rs {
            for &(t, wt) in &rt {
                let (x, jac) = param(p, s, t);
                let f: f64 = tris
                    .iter()
                    .map(|&tr| inner(x, n_x, tr, n_y, &rule, 0))
                    .sum();
                sum += ws * wt * jac * f;
            }
        }
        sum
    }

    fn quadrature(c: &Case) -> f64 {
        let pairs = c.visible_pairs();
        pairs.iter().map(|(p, q)| area_factor(p, q)).sum::<f64>() / from_area(c)
    }

    #[test]
    fn catalogue_is_well_formed() {
        let cases = all();
        assert!(cases.len() >= 40, "{} cases", cases.len());
        let classes: BTreeSet<Class> = cases.iter().map(|c| c.class).collect();
        assert!(classes.len() >= 8, "{classes:?}");
        let mut names = BTreeSet::new();
        for c in &cases {
            assert!(names.insert(c.name.clone()), "repeated case {}", c.name);
            assert!(
                c.from != c.to && c.exact > 0.0 && c.exact <= 1.0 + 1e-15,
                "{}",
                c.name
            );
            assert!(!c.source.is_empty(), "{}", c.name);
            let mut surfaces = BTreeSet::new();
            for s in &c.surfaces {
                assert!(
                    surfaces.insert(s.name.clone()),
                    "{}: repeated {}",
                    c.name,
                    s.name
                );
                for p in &s.polygons {
                    assert!(p.len() == 3 || p.len() == 4, "{}", c.name);
                    if p.len() == 4 {
                        let skew = (p[0] + p[2] - p[1] - p[3]).length();
                        assert!(
                            skew < 1e-9 * (p[1] - p[0]).length(),
                            "{}: not a parallelogram",
                            c.name
                        );
                    }
                }
            }
            // The visible pairs lie on the compared surfaces: their areas add up to at
            // most the from-surface's.
            let vis: f64 = c.visible.iter().map(|(p, _)| polygon_area(p)).sum();
            assert!(vis <= from_area(c) * (1.0 + 1e-12), "{}", c.name);
        }
    }

    #[test]
    fn exact_values_match_independent_quadrature() {
        let cases = all();
        let rows: Vec<(String, f64, f64)> = cases
            .par_iter()
            .map(|c| {
                let q = quadrature(c);
                (c.name.clone(), c.exact, q)
            })
            .collect();
        let mut worst: f64 = 0.0;
        let mut bad = Vec::new();
        for (name, exact, q) in &rows {
            let rel = (q - exact).abs() / exact;
            eprintln!("{name:<28} exact {exact:.15} quadrature {q:.15} relative {rel:.1e}");
            worst = worst.max(rel);
            if rel > 1e-6 {
                bad.push(name.clone());
            }
        }
        eprintln!("worst relative difference {worst:.2e}");
        assert!(bad.is_empty(), "closed form and quadrature differ: {bad:?}");
    }
}
