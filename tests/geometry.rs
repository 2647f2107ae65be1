//! Geometry is exact to f64: the semi-analytic factor of a closed-form case does not change
//! (to 1e-12 relative), nor casts rays, when the scene is moved rigidly or scaled, and two
//! plates closer than the ray offset still see each other.

use glam::{DQuat, DVec3};
use radiosity::analytic::{parallel_rectangles, perpendicular_rectangles};
use radiosity::formfactor::{compute, Context, Nodes, SemiAnalytic};
use radiosity::mesh::{PatchSet, Resolution};
use radiosity::sampling::Pcg32;
use radiosity::scene::Scene;
use radiosity::study::configs;
use radiosity::visibility::Visibility;

/// `(F_ij, rays cast)` of the semi-analytic estimator at relative tolerance `tol`, one patch
/// per face.
fn semi(scene: &Scene, i: usize, j: usize, tol: f64) -> (f64, u64) {
    let patches = PatchSet::build(scene, Resolution::MaxEdge(1e30)).expect("patches");
    assert_eq!(patches.len(), scene.faces.len());
    let vis = Visibility::new(&patches).expect("visibility");
    let ctx = Context {
        patches: &patches,
        vis: &vis,
        seed: 1,
    };
    let est = SemiAnalytic::new(Nodes::Gauss, 4, 4, 4).with_tol(tol);
    let ff = compute(&ctx, &est, &|_| {});
    (ff.get(i, j), ff.rays)
}

/// `scene` scaled by `s` about the origin, rotated by `q`, then moved by `t`.
fn moved(scene: &Scene, s: f64, q: DQuat, t: DVec3) -> Scene {
    let mut out = scene.clone();
    for p in &mut out.positions {
        *p = q * (*p * s) + t;
    }
    out
}

/// A uniformly random rotation (Shoemake 1992, "Uniform random rotations").
fn rotation(rng: &mut Pcg32) -> DQuat {
    let (u1, u2, u3) = (rng.next_f64(), rng.next_f64(), rng.next_f64());
    let tau = std::f64::consts::TAU;
    let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
    DQuat::from_xyzw(
        a * (tau * u2).sin(),
        a * (tau * u2).cos(),
        b * (tau * u3).sin(),
        b * (tau * u3).cos(),
    )
    .normalize()
}

/// Howell C-11 and C-14 and the study's catalogue of closed forms (every case nothing
/// blocks), each under 20 random rigid motions at scales 1, 1e-6 and 1e6: the factor equals
/// the canonical placement's to 1e-12 relative, no ray is cast (none is in canonical
/// placement), and the factor meets the tolerance 1e-9 against the closed form.
#[test]
fn closed_forms_are_invariant_under_rigid_motions_and_scaling() {
    let mut cases: Vec<(String, Scene, usize, usize, f64)> = Vec::new();
    for (name, exact) in [
        ("plates-parallel", parallel_rectangles(1.0, 1.0, 1.0)),
        (
            "plates-perpendicular",
            perpendicular_rectangles(1.0, 1.0, 1.0),
        ),
    ] {
        cases.push((name.into(), Scene::load(name).unwrap(), 0, 1, exact));
    }
    for c in configs::all().into_iter().filter(|c| c.unoccluded) {
        cases.push((c.name.into(), c.scene, c.i, c.j, c.exact));
    }
    let tol = 1e-9;
    let mut rng = Pcg32::keyed(2024, 12, 0, 0);
    let (mut worst_motion, mut worst_exact) = (0.0f64, 0.0f64);
    for (name, scene, i, j, exact) in &cases {
        let (f0, rays0) = semi(scene, *i, *j, tol);
        assert_eq!(rays0, 0, "{name}: canonical placement casts rays");
        let err = (f0 - exact).abs() / exact;
        worst_exact = worst_exact.max(err);
        assert!(err <= tol, "{name}: F = {f0} vs exact {exact} ({err:.1e})");
        for k in 0..20 {
            let q = rotation(&mut rng);
            let t = DVec3::new(rng.next_f64(), rng.next_f64(), rng.next_f64()) * 20.0 - 10.0;
            for s in [1.0, 1e-6, 1e6] {
                let (f, rays) = semi(&moved(scene, s, q, t * s), *i, *j, tol);
                let rel = (f - f0).abs() / f0;
                worst_motion = worst_motion.max(rel);
                assert_eq!(rays, 0, "{name}, motion {k}, scale {s}: {rays} rays");
                assert!(
                    rel <= 1e-12,
                    "{name}, motion {k}, scale {s}: {f} vs canonical {f0} ({rel:.1e})"
                );
                let err = (f - exact).abs() / exact;
                assert!(err <= tol, "{name}, motion {k}, scale {s}: {err:.1e}");
            }
        }
    }
    eprintln!(
        "{} cases x 20 motions x 3 scales: worst change {worst_motion:.1e}, \
         worst error against the closed forms {worst_exact:.1e}",
        cases.len()
    );
}

/// Two facing unit plates 1e-6 apart (far closer than the scene's ray offset, 1e-5 of its
/// diagonal) see each other: F = 0.999998 (Howell C-11), not 0.
#[test]
fn plates_closer_than_the_ray_offset_see_each_other() {
    let gap = 1e-6;
    let mut scene = Scene::load("plates-parallel").unwrap();
    let z: Vec<f64> = scene.positions.iter().map(|p| p.z).collect();
    let top = z.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    for p in &mut scene.positions {
        if p.z == top {
            p.z = gap;
        }
    }
    let exact = parallel_rectangles(1.0, 1.0, gap);
    assert!((exact - 0.999998).abs() < 1e-6, "{exact}");
    let patches = PatchSet::build(&scene, Resolution::MaxEdge(1e30)).unwrap();
    let vis = Visibility::new(&patches).unwrap();
    let ctx = Context {
        patches: &patches,
        vis: &vis,
        seed: 1,
    };
    let f = compute(&ctx, &SemiAnalytic::default(), &|_| {});
    let (f01, f10) = (f.get(0, 1), f.get(1, 0));
    eprintln!("plates {gap} apart: F = {f01} (exact {exact})");
    assert!(
        (f01 - exact).abs() < 1e-5 && (f10 - exact).abs() < 1e-5,
        "{f01} {f10}"
    );
    // And a segment across the gap is free: both ends stay between the plates.
    let (n0, n1) = (patches.normal[0], patches.normal[1]);
    let (x, y) = (patches.centroid[0], patches.centroid[1]);
    let mut seen = [false];
    vis.segments_visible(&[vis.segment_ray(x, n0, y, n1)], &mut seen);
    assert!(seen[0], "the segment across the gap is blocked");
}
