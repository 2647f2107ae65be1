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

/// `(1/A_e) ∫_{A_e} F(x → P_r) dA_x` between two convex polygons that nothing blocks, by
/// the crate's deterministic integral ([`radiosity::formfactor::exact`]) over a fan of the
/// emitter to the relative tolerance 1e-12: the exact value of polygons that are not in
/// any catalogue (a 128-gon, a tiny square).
fn polygon_exact(emitter: &[DVec3], receiver: &[DVec3]) -> f64 {
    use radiosity::formfactor::exact::{integrate, Contact, Emitter, Piece, Receiver};
    let normal = |p: &[DVec3]| {
        (1..p.len() - 1)
            .map(|k| (p[k] - p[0]).cross(p[k + 1] - p[0]))
            .sum::<DVec3>()
    };
    let (ne, nr) = (normal(emitter), normal(receiver));
    let centroid = receiver.iter().sum::<DVec3>() / receiver.len() as f64;
    let recv = Receiver::new(receiver, nr.normalize(), centroid);
    let mut total = 0.0;
    for k in 1..emitter.len() - 1 {
        let tri = Piece::Tri([emitter[0], emitter[k], emitter[k + 1]]);
        // Only the value is used: the contact's kind changes the reported bound alone.
        let em = &mut Emitter::new(tri);
        total += integrate(em, ne.normalize(), &recv, 1e-12, 0.0, &|| Contact::Kinked).value;
    }
    total / (0.5 * ne.length())
}

/// A scene of two convex polygons (objects `a` and `b`: the loader splits a polygon into
/// triangles and quads) written as OBJ.
fn two_polygons(dir: &std::path::Path, name: &str, a: &[DVec3], b: &[DVec3]) -> Scene {
    let mut obj = String::new();
    for v in a.iter().chain(b) {
        obj += &format!("v {:.17e} {:.17e} {:.17e}\n", v.x, v.y, v.z);
    }
    let face = |lo: usize, n: usize| {
        (lo..lo + n)
            .map(|k| (k + 1).to_string())
            .collect::<Vec<_>>()
            .join(" ")
    };
    obj += &format!(
        "o a\nf {}\no b\nf {}\n",
        face(0, a.len()),
        face(a.len(), b.len())
    );
    let path = dir.join(format!("{name}.obj"));
    std::fs::write(&path, obj).expect("write the scene");
    Scene::load(path.to_str().expect("utf-8 path")).expect("scene")
}

/// A regular `n`-gon of radius `r` in the plane `z`, counter-clockwise seen from `+z` when
/// `up` (normal `+z`), else clockwise (normal `-z`).
fn ngon(n: usize, r: f64, z: f64, up: bool) -> Vec<DVec3> {
    let mut p: Vec<DVec3> = (0..n)
        .map(|k| {
            let t = std::f64::consts::TAU * k as f64 / n as f64;
            DVec3::new(r * t.cos(), r * t.sin(), z)
        })
        .collect();
    if !up {
        p.reverse();
    }
    p
}

/// A rectangle `[x0, x1] x [y0, y1]` in the plane `z`, normal `+z` when `up`, else `-z`.
fn rect(x: [f64; 2], y: [f64; 2], z: f64, up: bool) -> Vec<DVec3> {
    let mut p = vec![
        DVec3::new(x[0], y[0], z),
        DVec3::new(x[1], y[0], z),
        DVec3::new(x[1], y[1], z),
        DVec3::new(x[0], y[1], z),
    ];
    if !up {
        p.reverse();
    }
    p
}

/// The acceptance test of the error bars: closed-form cases under random rigid motions,
/// every randomized estimator at the command line's default settings (`--samples 3
/// --rays 2 --replicates 4 --tol 1e-6`), each estimate of face `i` to face `j` (the
/// area-weighted sum over the faces' patches, with its bar summed as every surface sum is:
/// standard errors in quadrature, bounds linearly, [`radiosity::objects::lump`]) checked
/// against its bar: `|F - F_exact| <= t s + b`.
///
/// The cases: the study's seven configurations (adjacent, near, far, grazing and
/// small-large rectangle pairs, the occluded pair split by a divider, the shelf), two
/// coaxial 128-gons of radius 1 one apart (exact: the polygons' own integral, not the
/// disks' closed form, which is 0.4% higher), strips 4 x 0.5 facing each other 0.5 apart,
/// and a 0.01 square under the centre of a unit square 1 away (point to rectangle).
///
/// The false-alarm rate: standard errors come from 4 replicates, so `(F - F_exact) / s` of
/// an honest estimate is at most Student-t with 3 degrees of freedom (a sum over several
/// entries has more: Welch–Satterthwaite; 3 is the conservative count); bounds and the
/// bar of unhit pairs hold without a share of the rate. Each of the `K` checks is allowed
/// the two-sided t₃ quantile of tail `α / K` (Bonferroni), `α = 1e-2` for the whole test.
/// The hemicube is left out: it reports no bar (its errors are deterministic biases,
/// docs/ESTIMATORS.md).
#[test]
fn every_estimator_is_within_its_bar_under_rigid_motions() {
    use radiosity::pipeline::{self, EstimatorChoice, Quiet};
    use statrs::distribution::{ContinuousCDF, StudentsT};
    let dir = std::env::temp_dir().join(format!("radiosity-rigid-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    // (name, scene, i, j, exact, i and j are objects rather than faces)
    let mut cases: Vec<(String, Scene, usize, usize, f64, bool)> = configs::all()
        .into_iter()
        .map(|c| (c.name.to_string(), c.scene, c.i, c.j, c.exact, false))
        .collect();
    let (da, db) = (ngon(128, 1.0, 0.0, true), ngon(128, 1.0, 1.0, false));
    let disk = polygon_exact(&da, &db);
    // The 128-gon's factor is below the disks' closed form (Howell C-41), by its smaller
    // area's share.
    let closed = 0.5 * (3.0 - 5f64.sqrt());
    assert!(
        disk < closed && disk > 0.99 * closed,
        "{disk} vs disks {closed}"
    );
    let disks = two_polygons(&dir, "disks", &da, &db);
    cases.push(("128-gons".into(), disks, 0, 1, disk, true));
    let (sa, sb) = (
        rect([0.0, 4.0], [0.0, 0.5], 0.0, true),
        rect([0.0, 4.0], [0.0, 0.5], 0.5, false),
    );
    let strips = polygon_exact(&sa, &sb);
    assert!((strips - parallel_rectangles(4.0, 0.5, 0.5)).abs() < 1e-10);
    let pair = two_polygons(&dir, "strips", &sa, &sb);
    cases.push(("strips".into(), pair, 0, 1, strips, true));
    let (ta, tb) = (
        rect([-0.005, 0.005], [-0.005, 0.005], 0.0, true),
        rect([-0.5, 0.5], [-0.5, 0.5], 1.0, false),
    );
    let tiny = polygon_exact(&ta, &tb);
    let pair = two_polygons(&dir, "tiny", &ta, &tb);
    cases.push(("tiny-to-square".into(), pair, 0, 1, tiny, true));
    let (strata, replicates) = (3, 4);
    let estimators = [
        EstimatorChoice::AreaUniform { strata, replicates },
        EstimatorChoice::AreaStratified { strata, replicates },
        EstimatorChoice::AreaSobol { strata, replicates },
        EstimatorChoice::Hemisphere { strata, replicates },
        EstimatorChoice::SemiAnalytic {
            points: strata,
            rays: 2,
            replicates,
            tol: 1e-6,
        },
    ];
    let motions = 4;
    let checks = cases.len() * motions * estimators.len();
    let alpha = 1e-2;
    let t3 = StudentsT::new(0.0, 1.0, (replicates - 1) as f64).expect("t");
    let k = t3.inverse_cdf(1.0 - alpha / (2.0 * checks as f64));
    let mut rng = Pcg32::keyed(2026, 14, 0, 0);
    let (mut failures, mut worst) = (Vec::new(), Vec::new());
    for (name, scene, i, j, exact, by_object) in &cases {
        for m in 0..motions {
            let q = rotation(&mut rng);
            let t = DVec3::new(rng.next_f64(), rng.next_f64(), rng.next_f64()) * 20.0 - 10.0;
            let scene = moved(scene, 1.0, q, t);
            let patches = PatchSet::build(&scene, Resolution::MaxEdge(1e30)).expect("patches");
            let (group, groups) = if *by_object {
                (&patches.object, patches.objects.len())
            } else {
                (&patches.face, scene.faces.len())
            };
            for (e, est) in estimators.iter().enumerate() {
                let seed = 100 * m as u64 + e as u64;
                let (ff, _, _) =
                    pipeline::form_factors(&patches, est, seed, &Quiet).expect("factors");
                let (zf, bars, _) =
                    radiosity::objects::lump(&ff.f, &ff.se, &ff.area, group, groups).expect("lump");
                let (f, mut bar) = match zf.nnz_index(*i, *j) {
                    Some(k) => (zf.data()[k.0], bars[k.0]),
                    None => (0.0, radiosity::matrix::Bar::ZERO),
                };
                // The unstored pairs between the two faces: no ray hit them (hemisphere
                // shooting), their bar is the unresolved one.
                if ff.unresolved > 0.0 {
                    bar.se = bar.se.hypot(ff.unresolved);
                }
                let err = (f - exact).abs();
                let allowed = bar.allowance(k);
                worst.push((
                    err / allowed.max(f64::MIN_POSITIVE),
                    name.clone(),
                    ff.estimator.clone(),
                ));
                if err.is_nan() || err > allowed {
                    failures.push(format!(
                        "{name}, motion {m}, {}: F = {f:.9} {bar} vs exact {exact:.9} \
                         (error {err:.2e} > {k:.1} s.e. + bound = {allowed:.2e})",
                        ff.estimator
                    ));
                }
            }
        }
    }
    std::fs::remove_dir_all(&dir).ok();
    worst.sort_by(|a, b| b.0.total_cmp(&a.0));
    eprintln!(
        "{checks} checks at {k:.1} standard errors plus bounds (t3, family-wise 1e-2); \
         largest |error| / allowance: {:?}",
        &worst[..3.min(worst.len())]
    );
    assert!(failures.is_empty(), "{failures:#?}");
}
