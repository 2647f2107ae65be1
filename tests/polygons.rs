//! Polygons meshed as written: the L-shaped floor keeps its area exactly, and a disk
//! written as one 128-corner face bakes as accurately as the same disk written as a polar
//! grid (`scenes/disks-ngon.obj`, `scenes/disks-polar.obj`, from `scripts/disks.py`),
//! against the exact factor between the two 128-gons.

use std::path::Path;
use std::time::Instant;

use glam::DVec3;
use radiosity::analytic::{coaxial_disks, gauss_legendre, point_to_polygon};
use radiosity::mesh::{PatchSet, Resolution};
use radiosity::pipeline::{self, BakeConfig, Quiet};
use radiosity::scene::polygon::newell;
use radiosity::scene::Scene;

fn scene(name: &str) -> Scene {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name);
    Scene::load(path.to_str().expect("utf-8 path")).expect("scene loads")
}

/// Area and summed Newell normal of the faces of `material`.
fn faces_of(s: &Scene, material: &str) -> (f64, DVec3) {
    let m = s.material_index(material).expect("material") as u32;
    let mut area = 0.0;
    let mut normal = DVec3::ZERO;
    for f in s.faces.iter().filter(|f| f.material == m) {
        let p: Vec<DVec3> = f
            .corner_slice()
            .iter()
            .map(|&c| s.positions[c as usize])
            .collect();
        let n = newell(&p);
        area += 0.5 * n.length();
        normal += n;
    }
    (area, normal)
}

/// The regular 128-gon of the fixtures (circumradius 1 at height `y`).
fn ngon(y: f64) -> Vec<DVec3> {
    (0..128)
        .map(|k| {
            let t = std::f64::consts::TAU * k as f64 / 128.0;
            DVec3::new(t.cos(), y, -t.sin())
        })
        .collect()
}

/// The exact factor from the receiver 128-gon (y = 1, facing down) to the emitter one
/// (y = 0): the exact point-to-polygon factor (Lambert's contour integral) integrated over
/// the receiver by Gauss-Legendre (on [0, 1]) on the 128 triangles around its centre (a smooth
/// integrand: the polygons are a radius apart), to about 1e-14.
fn exact_ngon_factor() -> f64 {
    let (rx, em) = (ngon(1.0), ngon(0.0));
    let gl = gauss_legendre(24);
    let c = DVec3::new(0.0, 1.0, 0.0);
    let mut sum = 0.0;
    let mut area = 0.0;
    for k in 0..128 {
        let (a, b) = (rx[k], rx[(k + 1) % 128]);
        let tri = 0.5 * (a - c).cross(b - c).length();
        area += tri;
        // Duffy: x = c + s (a - c) + s t (b - a), dA = 2 A s ds dt on the unit square.
        for &(s, ws) in &gl {
            for &(t, wt) in &gl {
                let x = c + (a - c) * s + (b - a) * (s * t);
                let w = ws * wt * 2.0 * tri * s;
                sum += w * point_to_polygon(x, -DVec3::Y, &em);
            }
        }
    }
    sum / area
}

#[test]
fn l_shaped_floor_keeps_its_area() {
    let s = scene("l-floor.obj");
    let (area, normal) = faces_of(&s, "floor");
    assert_eq!(area, 7.0, "the floor is 7 m^2");
    assert!(normal.normalize().dot(DVec3::Y) > 1.0 - 1e-15);
    let patches = PatchSet::build(&s, Resolution::Patches(200)).expect("patches");
    let m = s.material_index("floor").expect("floor") as u32;
    let patch_area: f64 = (0..patches.len())
        .filter(|&i| patches.material[i] == m)
        .map(|i| patches.area[i])
        .sum();
    assert!((patch_area - 7.0).abs() < 1e-12, "{patch_area}");
}

#[test]
fn disk_as_one_face_bakes_like_the_polar_grid() {
    let exact = exact_ngon_factor();
    let disk = coaxial_disks(1.0, 1.0, 1.0);
    eprintln!("F(128-gon -> 128-gon) = {exact:.12} (disks: {disk:.12})");
    // The 128-gon holds 0.9996 of the disk's area; the factors differ by about that.
    assert!((exact - disk).abs() < 1e-3, "{exact} vs {disk}");
    let ngon_area = 0.5 * newell(&ngon(0.0)).length();
    let mut errors = Vec::new();
    for name in ["disks-ngon.obj", "disks-polar.obj"] {
        let s = scene(name);
        for material in ["lamp", "grey"] {
            let (area, normal) = faces_of(&s, material);
            assert!(
                (area - ngon_area).abs() < 1e-13,
                "{name} {material}: {area} vs {ngon_area}"
            );
            assert!((normal.length() - 2.0 * ngon_area).abs() < 1e-12);
        }
        let cfg = BakeConfig {
            resolution: Resolution::Patches(1000),
            ..BakeConfig::default()
        };
        let start = Instant::now();
        let patches = PatchSet::build(&s, cfg.resolution).expect("patches");
        let (ff, _, _) =
            pipeline::form_factors(&patches, &cfg.estimator, cfg.seed, &Quiet).expect("factors");
        let (b, _) =
            pipeline::solve_radiosity(&patches, &ff, cfg.method, &cfg.solve).expect("solve");
        let seconds = start.elapsed().as_secs_f64();
        // The emitter reflects nothing, so the receiver's B is rho F E: its area-weighted
        // mean over rho E is the receiver's factor to the emitter.
        let grey = s.material_index("grey").expect("grey") as u32;
        let (mut fa, mut a) = (0.0, 0.0);
        for i in (0..patches.len()).filter(|&i| patches.material[i] == grey) {
            fa += patches.area[i] * b[i][0] / 0.5;
            a += patches.area[i];
        }
        let f = fa / a;
        let worst_angle = (0..patches.len())
            .map(|i| {
                let (p, n) = patches.corner_points(i);
                (0..n)
                    .map(|k| {
                        let (u, v) = (p[(k + 1) % n] - p[k], p[(k + n - 1) % n] - p[k]);
                        u.angle_between(v).to_degrees()
                    })
                    .fold(180.0, f64::min)
            })
            .fold(180.0, f64::min);
        eprintln!(
            "{name}: {} faces, {} patches, smallest patch angle {worst_angle:.1} deg, F = \
             {f:.12}, error {:.2e}, {seconds:.2} s",
            s.faces.len(),
            patches.len(),
            (f - exact).abs()
        );
        errors.push((f - exact).abs());
    }
    // As accurate as the polar grid (which has slivers of its own at the centre); both
    // well inside the semi estimator's tolerance.
    assert!(errors[0] <= 2.0 * errors[1] + 1e-9, "{errors:?}");
    assert!(errors[0] < 1e-5, "{errors:?}");
}
