//! Generated scenes of many small faces, for the hierarchical solver's clustering and its
//! scaling measurements: `room-spheres-N`, a 5 x 3 x 4 m room lit by a 1 x 1 m ceiling
//! light with `N` grey spheres of 1280 triangles each (icospheres, three subdivisions of
//! the icosahedron) floating on a regular grid below the light; `room-spheres-N-sL` the
//! same room and spheres with `L` subdivisions (`20·4^L` triangles a sphere). The two
//! families grow a scene in the two ways models grow: more objects (more of the light's
//! interactions), or the same objects more finely tessellated (the same light, more
//! faces: a scanned or subdivided model). The scene depends only on its name: the same
//! name gives the same triangles, bit for bit.
//!
//! The room matches `scenes/room-sphere.obj` (floor at y = 0, up +y, white walls of
//! reflectance 0.7, the wall at x = 0 pale blue, the light 1 cm below the ceiling,
//! emitting 10); spheres have reflectance 0.5.
//!
//! `city-N` is the other kind of scene: `N x N` box buildings standing on a ground plane
//! (every one meets the ground along its four base edges, so the scene is full of contact
//! edges and of shadows cast onto the streets), lit by an overcast sky: a quad 60 m up
//! that emits 1 downward and reflects nothing. Blocks are 10 m apart, buildings 6 x 6 m
//! with heights from 6 to 30 m drawn from a hash of their grid position; walls reflect
//! 0.6, roofs 0.5, the ground 0.3. Open at the sides, so part of the light escapes. Each
//! building is 5 quads (walls and roof; none under it), `10 N² + 4` triangles in all.

use std::fmt::Write;
use std::path::{Path, PathBuf};

use glam::DVec3;

use super::{obj, Scene};
use crate::error::Result;

/// Triangles per sphere of `room-spheres-N` (three subdivisions).
pub const SPHERE_TRIANGLES: usize = 1280;

/// Subdivisions of a sphere of `room-spheres-N`.
pub const SUBDIVISIONS: usize = 3;

/// Most spheres a name may ask for.
pub const MAX_SPHERES: usize = 4000;

/// Most subdivisions a name may ask for (`20·4^7` = 327,680 triangles a sphere).
pub const MAX_SUBDIVISIONS: usize = 7;

/// Most triangles a generated scene may have.
pub const MAX_TRIANGLES: usize = MAX_SPHERES * SPHERE_TRIANGLES;

/// The generated scenes listed by `radiosity scenes`: about 10^4, 3·10^4, 10^5, 3·10^5
/// and 10^6 triangles.
/// The second family: 12 spheres at 3 to 6 subdivisions, about 1.5·10^4 to 10^6
/// triangles.
pub const LISTED: &[&str] = &[
    "room-spheres-8",
    "room-spheres-24",
    "room-spheres-80",
    "room-spheres-240",
    "room-spheres-800",
    "room-spheres-12-s3",
    "room-spheres-12-s4",
    "room-spheres-12-s5",
    "room-spheres-12-s6",
];

/// Most buildings per side of `city-N` (`10 · 320² + 4` = 1,024,004 triangles).
pub const MAX_CITY: usize = 320;

/// The generated city scenes listed by `radiosity scenes`: about 10^4, 10^5 and 10^6
/// triangles.
pub const LISTED_CITY: &[&str] = &["city-32", "city-100", "city-316"];

/// Buildings per side a `city-N` name asks for, if it names one.
pub fn city(name: &str) -> Option<usize> {
    let n: usize = name.strip_prefix("city-")?.parse().ok()?;
    (1..=MAX_CITY).contains(&n).then_some(n)
}

/// Triangles of `city-N`: 5 quads a building, the ground and the sky.
pub fn city_triangles(n: usize) -> usize {
    10 * n * n + 4
}

/// Triangles of an icosphere of `l` subdivisions.
pub fn sphere_triangles(l: usize) -> usize {
    20 << (2 * l)
}

/// The number of spheres and their subdivisions a generated scene's name asks for, if it
/// names one: `room-spheres-N` (three subdivisions) or `room-spheres-N-sL`.
pub fn spheres(name: &str) -> Option<(usize, usize)> {
    let rest = name.strip_prefix("room-spheres-")?;
    let (n, l) = match rest.split_once("-s") {
        Some((n, l)) => (n.parse().ok()?, l.parse().ok()?),
        None => (rest.parse().ok()?, SUBDIVISIONS),
    };
    ((1..=MAX_SPHERES).contains(&n)
        && l <= MAX_SUBDIVISIONS
        && n * sphere_triangles(l) <= MAX_TRIANGLES)
        .then_some((n, l))
}

/// One line on a generated scene (`radiosity scenes`).
pub fn describe(name: &str) -> Option<String> {
    if let Some(n) = city(name) {
        return Some(format!(
            "city block, {n} x {n} buildings on the ground under an overcast sky: {} triangles",
            city_triangles(n)
        ));
    }
    let (n, l) = spheres(name)?;
    Some(format!(
        "room, ceiling light, {n} spheres of {} triangles: {} triangles, 7 quads",
        sphere_triangles(l),
        n * sphere_triangles(l)
    ))
}

const MTL: &str = "newmtl white\nKd 0.7 0.7 0.7\nnewmtl blue\nKd 0.6 0.65 0.7\n\
newmtl grey\nKd 0.5 0.5 0.5\nnewmtl light\nKd 0.78 0.78 0.78\nKe 10 10 10\n";

/// The unit icosphere: vertices and outward (counter-clockwise from outside) triangles.
pub fn icosphere(subdivisions: usize) -> (Vec<DVec3>, Vec<[usize; 3]>) {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut v: Vec<DVec3> = [
        (-1.0, t, 0.0),
        (1.0, t, 0.0),
        (-1.0, -t, 0.0),
        (1.0, -t, 0.0),
        (0.0, -1.0, t),
        (0.0, 1.0, t),
        (0.0, -1.0, -t),
        (0.0, 1.0, -t),
        (t, 0.0, -1.0),
        (t, 0.0, 1.0),
        (-t, 0.0, -1.0),
        (-t, 0.0, 1.0),
    ]
    .iter()
    .map(|&(x, y, z)| DVec3::new(x, y, z).normalize())
    .collect();
    let mut f: Vec<[usize; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdivisions {
        let mut mid = std::collections::HashMap::new();
        let mut next = Vec::with_capacity(f.len() * 4);
        let mut midpoint = |a: usize, b: usize, v: &mut Vec<DVec3>| -> usize {
            *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                v.push(((v[a] + v[b]) * 0.5).normalize());
                v.len() - 1
            })
        };
        for &[a, b, c] in &f {
            let ab = midpoint(a, b, &mut v);
            let bc = midpoint(b, c, &mut v);
            let ca = midpoint(c, a, &mut v);
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        f = next;
    }
    // Outward: the normal agrees with the centroid's direction.
    for t in &mut f {
        let (a, b, c) = (v[t[0]], v[t[1]], v[t[2]]);
        if (b - a).cross(c - a).dot(a + b + c) < 0.0 {
            t.swap(1, 2);
        }
    }
    (v, f)
}

/// Centres and radius of `n` spheres on a regular grid inside the room, below the light.
pub fn placement(n: usize) -> (Vec<DVec3>, f64) {
    let (lo, hi) = (DVec3::new(0.4, 0.3, 0.4), DVec3::new(4.6, 2.5, 3.6));
    let ext = hi - lo;
    // Cells as close to cubes as the count allows.
    let side = (ext.x * ext.y * ext.z / n as f64).cbrt();
    let mut dims = [
        (ext.x / side).round().max(1.0) as usize,
        (ext.y / side).round().max(1.0) as usize,
        (ext.z / side).round().max(1.0) as usize,
    ];
    while dims[0] * dims[1] * dims[2] < n {
        // Grow the axis with the largest cells.
        let k = (0..3)
            .max_by(|&a, &b| (ext[a] / dims[a] as f64).total_cmp(&(ext[b] / dims[b] as f64)))
            .unwrap_or(0);
        dims[k] += 1;
    }
    let cell = DVec3::new(
        ext.x / dims[0] as f64,
        ext.y / dims[1] as f64,
        ext.z / dims[2] as f64,
    );
    let radius = 0.35 * cell.min_element();
    let mut centres = Vec::with_capacity(n);
    'fill: for j in 0..dims[1] {
        for k in 0..dims[2] {
            for i in 0..dims[0] {
                if centres.len() == n {
                    break 'fill;
                }
                let c = DVec3::new(i as f64 + 0.5, j as f64 + 0.5, k as f64 + 0.5);
                centres.push(lo + c * cell);
            }
        }
    }
    (centres, radius)
}

/// The OBJ text of `n` spheres of `l` subdivisions in the room.
pub fn obj_text(n: usize, l: usize) -> String {
    let mut o = String::new();
    let _ = writeln!(
        o,
        "# room-spheres-{n}-s{l}: generated (radiosity::scene::generated)\nmtllib generated.mtl"
    );
    let quads: [(&str, &str, [[f64; 3]; 4]); 7] = [
        (
            "floor",
            "white",
            [[0., 0., 0.], [0., 0., 4.], [5., 0., 4.], [5., 0., 0.]],
        ),
        (
            "ceiling",
            "white",
            [[0., 3., 0.], [5., 3., 0.], [5., 3., 4.], [0., 3., 4.]],
        ),
        (
            "wall_z0",
            "white",
            [[0., 0., 0.], [5., 0., 0.], [5., 3., 0.], [0., 3., 0.]],
        ),
        (
            "wall_z4",
            "white",
            [[0., 0., 4.], [0., 3., 4.], [5., 3., 4.], [5., 0., 4.]],
        ),
        (
            "wall_x0",
            "blue",
            [[0., 0., 0.], [0., 3., 0.], [0., 3., 4.], [0., 0., 4.]],
        ),
        (
            "wall_x5",
            "white",
            [[5., 0., 0.], [5., 0., 4.], [5., 3., 4.], [5., 3., 0.]],
        ),
        (
            "light",
            "light",
            [
                [2., 2.99, 1.5],
                [3., 2.99, 1.5],
                [3., 2.99, 2.5],
                [2., 2.99, 2.5],
            ],
        ),
    ];
    let mut base = 1;
    for (name, mtl, q) in quads {
        let _ = writeln!(o, "o {name}\nusemtl {mtl}");
        push_quad(&mut o, &mut base, q);
    }
    let (v, f) = icosphere(l);
    let (centres, radius) = placement(n);
    for (k, c) in centres.iter().enumerate() {
        let _ = writeln!(o, "o sphere_{k}\nusemtl grey");
        for p in &v {
            let q = *c + *p * radius;
            let _ = writeln!(o, "v {:.9} {:.9} {:.9}", q.x, q.y, q.z);
        }
        for t in &f {
            let _ = writeln!(o, "f {} {} {}", base + t[0], base + t[1], base + t[2]);
        }
        base += v.len();
    }
    o
}

/// Writes quad `q` as four `v` lines and one `f` line whose corners are numbered from
/// `base` (1-based, as OBJ counts), and moves `base` past them.
fn push_quad(o: &mut String, base: &mut usize, q: [[f64; 3]; 4]) {
    for p in q {
        let _ = writeln!(o, "v {} {} {}", p[0], p[1], p[2]);
    }
    let b = *base;
    let _ = writeln!(o, "f {} {} {} {}", b, b + 1, b + 2, b + 3);
    *base += 4;
}

const CITY_MTL: &str = "newmtl ground\nKd 0.3 0.3 0.3\nnewmtl wall\nKd 0.6 0.6 0.6\n\
newmtl roof\nKd 0.5 0.5 0.5\nnewmtl sky\nKd 0 0 0\nKe 1 1 1\n";

/// Grid pitch of the buildings (footprint plus street), metres.
const PITCH: f64 = 10.0;
/// Side of a building's square footprint.
const FOOT: f64 = 6.0;
/// Height of the sky quad.
const SKY: f64 = 60.0;

/// Height of building `(i, j)` of a city: 6 to 30 m, from a hash of its position only.
pub fn building_height(i: usize, j: usize) -> f64 {
    let mut r = crate::sampling::Pcg32::keyed(0x6369_7479, i as u64, j as u64, 0);
    6.0 + 24.0 * r.next_f64()
}

/// The OBJ text of `city-N`. Quads are counter-clockwise seen from their front: the ground
/// and roofs face up, the sky down, walls out.
pub fn city_text(n: usize) -> String {
    let mut o = String::new();
    let _ = writeln!(
        o,
        "# city-{n}: generated (radiosity::scene::generated)\nmtllib city.mtl"
    );
    let l = n as f64 * PITCH;
    // Seen from a corner, under the sky (from outside, the sky would hide the streets).
    let _ = writeln!(
        o,
        "#@camera eye {} {} {} target {} 0 {} up 0 1 0 fov 60",
        -0.15 * l,
        0.6 * SKY,
        -0.15 * l,
        0.5 * l,
        0.5 * l
    );
    let mut base = 1;
    let mut quad = |o: &mut String, q: [[f64; 3]; 4]| push_quad(o, &mut base, q);
    let _ = writeln!(o, "o ground\nusemtl ground");
    quad(&mut o, [[0., 0., 0.], [0., 0., l], [l, 0., l], [l, 0., 0.]]);
    let (a, b) = (-PITCH, l + PITCH);
    let _ = writeln!(o, "o sky\nusemtl sky");
    quad(&mut o, [[a, SKY, a], [b, SKY, a], [b, SKY, b], [a, SKY, b]]);
    let inset = (PITCH - FOOT) / 2.0;
    for i in 0..n {
        for j in 0..n {
            let (x0, z0) = (i as f64 * PITCH + inset, j as f64 * PITCH + inset);
            let (x1, z1, h) = (x0 + FOOT, z0 + FOOT, building_height(i, j));
            let _ = writeln!(o, "o building_{i}_{j}\nusemtl wall");
            quad(
                &mut o,
                [[x0, 0., z0], [x0, h, z0], [x1, h, z0], [x1, 0., z0]],
            );
            quad(
                &mut o,
                [[x0, 0., z1], [x1, 0., z1], [x1, h, z1], [x0, h, z1]],
            );
            quad(
                &mut o,
                [[x0, 0., z0], [x0, 0., z1], [x0, h, z1], [x0, h, z0]],
            );
            quad(
                &mut o,
                [[x1, 0., z0], [x1, h, z0], [x1, h, z1], [x1, 0., z1]],
            );
            let _ = writeln!(o, "usemtl roof");
            quad(&mut o, [[x0, h, z0], [x0, h, z1], [x1, h, z1], [x1, h, z0]]);
        }
    }
    o
}

/// The generated scene `name`, or `None` when the name is not one.
pub fn load(name: &str) -> Result<Option<Scene>> {
    let (text, lib, mtl) = if let Some(n) = city(name) {
        (city_text(n), "city.mtl", CITY_MTL)
    } else if let Some((n, l)) = spheres(name) {
        (obj_text(n, l), "generated.mtl", MTL)
    } else {
        return Ok(None);
    };
    let label = PathBuf::from(format!("{name}.obj"));
    let mut scene = obj::parse(name, &label, &text, &|_lib: &str| {
        Ok((Path::new(lib).to_path_buf(), mtl.to_string()))
    })?;
    scene.source = format!("generated:{name}");
    Ok(Some(scene))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn icosphere_is_closed_outward_and_round() {
        let (v, f) = icosphere(SUBDIVISIONS);
        assert_eq!(f.len(), SPHERE_TRIANGLES);
        assert_eq!(sphere_triangles(SUBDIVISIONS), SPHERE_TRIANGLES);
        assert_eq!(v.len(), 642);
        // Every edge shared by exactly two triangles, in opposite directions.
        let mut edges = std::collections::HashMap::new();
        for t in &f {
            for k in 0..3 {
                *edges.entry((t[k], t[(k + 1) % 3])).or_insert(0) += 1;
            }
        }
        for (&(a, b), &c) in &edges {
            assert_eq!(c, 1);
            assert_eq!(edges.get(&(b, a)), Some(&1));
        }
        // Enclosed volume (divergence theorem) near the unit ball's, positive: outward.
        let vol: f64 = f
            .iter()
            .map(|t| v[t[0]].dot(v[t[1]].cross(v[t[2]])) / 6.0)
            .sum();
        assert!(
            (vol - 4.0 / 3.0 * std::f64::consts::PI).abs() < 0.05,
            "{vol}"
        );
    }

    #[test]
    fn spheres_fit_the_room_and_do_not_touch() {
        for n in [1, 8, 24, 80, 800] {
            let (c, r) = placement(n);
            assert_eq!(c.len(), n);
            for (i, a) in c.iter().enumerate() {
                assert!(a.x - r > 0.0 && a.x + r < 5.0 && a.z - r > 0.0 && a.z + r < 4.0);
                assert!(a.y - r > 0.0 && a.y + r < 2.99);
                for b in &c[..i] {
                    assert!(a.distance(*b) > 2.0 * r);
                }
            }
        }
    }

    #[test]
    fn names_give_the_same_scene() {
        assert_eq!(spheres("room-spheres-8"), Some((8, 3)));
        assert_eq!(spheres("room-spheres-12-s6"), Some((12, 6)));
        assert_eq!(spheres("room-spheres-2-s0"), Some((2, 0)));
        assert_eq!(spheres("room-spheres-0"), None);
        assert_eq!(spheres("room-spheres-x"), None);
        assert_eq!(spheres("room-spheres-8-s8"), None);
        assert_eq!(spheres("room-spheres-4000-s4"), None);
        assert_eq!(spheres("room-spheres-8-sx"), None);
        for name in LISTED {
            assert!(describe(name).is_some(), "{name}");
        }
        let c = load("room-spheres-1-s1").unwrap().unwrap();
        assert_eq!(c.faces.len(), 7 + 80);
        let a = load("room-spheres-2").unwrap().unwrap();
        let b = load("room-spheres-2").unwrap().unwrap();
        assert_eq!(a.faces.len(), 7 + 2 * SPHERE_TRIANGLES);
        assert_eq!(format!("{:?}", a.faces), format!("{:?}", b.faces));
        assert!(a.warnings.is_empty(), "{:?}", a.warnings);
        a.require_emitter().unwrap();
    }

    #[test]
    fn a_city_is_what_its_name_says_and_faces_out() {
        assert_eq!(city("city-32"), Some(32));
        assert_eq!(city("city-0"), None);
        assert_eq!(city("city-321"), None);
        assert_eq!(city("city-x"), None);
        let scene = load("city-3").unwrap().unwrap();
        let again = load("city-3").unwrap().unwrap();
        assert_eq!(
            scene.positions, again.positions,
            "the same name, the same scene"
        );
        let corners = |f: &super::super::Face| -> Vec<DVec3> {
            f.corners
                .iter()
                .filter(|&&k| k != super::super::Face::NONE)
                .map(|&k| scene.positions[k as usize])
                .collect()
        };
        let tris: usize = scene.faces.iter().map(|f| corners(f).len() - 2).sum();
        assert_eq!(tris, city_triangles(3));
        for name in LISTED_CITY {
            assert!(describe(name).is_some(), "{name}");
        }
        let (mut up, mut down, mut out) = (0, 0, 0);
        for f in &scene.faces {
            let p = corners(f);
            let n = (p[1] - p[0]).cross(p[2] - p[0]).normalize();
            let c = p.iter().copied().sum::<DVec3>() / p.len() as f64;
            if n.y > 0.999 {
                up += 1; // the ground and the roofs
            } else if n.y < -0.999 {
                down += 1; // the sky
                assert_eq!(c.y, SKY);
            } else {
                // A wall: its normal points away from its building's vertical axis.
                let (i, j) = ((c.x / PITCH).floor(), (c.z / PITCH).floor());
                let axis = DVec3::new((i + 0.5) * PITCH, c.y, (j + 0.5) * PITCH);
                assert!(n.dot(c - axis) > 0.0, "a wall facing in at {c}");
                let h = building_height(i as usize, j as usize);
                assert!((6.0..30.0).contains(&h));
                // It stands on the ground: a contact edge along y = 0.
                assert_eq!(p.iter().filter(|q| q.y == 0.0).count(), 2);
                out += 1;
            }
        }
        assert_eq!((up, down, out), (1 + 9, 1, 36));
    }
}
