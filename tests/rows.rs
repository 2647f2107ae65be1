//! Rows stay physical where patches touch or nearly touch: at the command line's default
//! settings no row of any estimator sums to more than 1 beyond chance, rows stay bounded,
//! and their bars cover the exact rows, on the notes' shelf (strips meeting at right
//! angles), on two strips meeting in a narrow wedge, and on two strips facing each other
//! across a thin gap. The area estimators' kernel is unbounded there; such pairs go to the
//! semi-analytic integral ([`radiosity::formfactor::area::near`]), by quadrature to a bound
//! where nothing can block them.

use radiosity::formfactor::area::{near, NEAR};
use radiosity::matrix::{over_one, Bar, FormFactors};
use radiosity::mesh::{PatchSet, Resolution};
use radiosity::pipeline::{self, EstimatorChoice, Quiet};
use radiosity::scene::Scene;

/// The command line's defaults (`--samples 3 --rays 2 --replicates 4 --tol 1e-6`).
fn defaults() -> Vec<EstimatorChoice> {
    let (strata, replicates) = (3, 4);
    vec![
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
    ]
}

/// Two strips 4 long and `w` wide along x: one in z = 0 facing +z, the other sharing its
/// edge y = 0 and opened by `angle` degrees (a wedge), or, for `gap`, parallel to it at
/// z = gap facing -z.
fn strips(dir: &std::path::Path, name: &str, w: f64, shape: Shape) -> String {
    let b = match shape {
        Shape::Wedge(deg) => {
            let (s, c) = deg.to_radians().sin_cos();
            // Corners 1 and 2 on the common edge; the normal (v1 - v0) x (v2 - v0) points
            // into the wedge, (0, sin, -cos).
            [
                [0.0, 0.0, 0.0],
                [0.0, w * c, w * s],
                [4.0, w * c, w * s],
                [4.0, 0.0, 0.0],
            ]
        }
        Shape::Gap(g) => [[0.0, 0.0, g], [0.0, w, g], [4.0, w, g], [4.0, 0.0, g]],
    };
    let a = [
        [0.0, 0.0, 0.0],
        [4.0, 0.0, 0.0],
        [4.0, w, 0.0],
        [0.0, w, 0.0],
    ];
    let mut obj = String::new();
    for v in a.iter().chain(&b) {
        obj += &format!("v {} {} {}\n", v[0], v[1], v[2]);
    }
    obj += "o a\nf 1 2 3 4\no b\nf 5 6 7 8\n";
    let path = dir.join(format!("{name}.obj"));
    std::fs::write(&path, obj).expect("write the scene");
    path.to_string_lossy().into_owned()
}

#[derive(Clone, Copy)]
enum Shape {
    Wedge(f64),
    Gap(f64),
}

/// Rows over 1 by more than `k` standard errors plus their bounds ([`over_one`]: the
/// entries' standard errors in quadrature, their bounds linearly).
fn rows_over(ff: &FormFactors, k: f64) -> Vec<(usize, f64, Bar)> {
    (0..ff.len())
        .filter_map(|i| {
            let (sum, bar) = (ff.row_sum(i), ff.row_sum_bar(i));
            over_one(sum, bar, k).then_some((i, sum, bar))
        })
        .collect()
}

#[test]
fn no_row_is_over_one_beyond_its_bars_where_patches_touch() {
    let dir = std::env::temp_dir().join(format!("radiosity-rows-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    // Each scene at the default resolution (1000 patches) and coarser, where the
    // patches are larger than the gaps between them.
    let scenes = [
        ("shelf".to_string(), Resolution::Patches(1000)),
        ("shelf".to_string(), Resolution::Patches(100)),
        (
            strips(&dir, "wedge", 0.5, Shape::Wedge(15.0)),
            Resolution::Patches(1000),
        ),
        (
            strips(&dir, "wedge", 0.5, Shape::Wedge(15.0)),
            Resolution::Patches(100),
        ),
        (
            strips(&dir, "gap", 1.0, Shape::Gap(0.06)),
            Resolution::Patches(1000),
        ),
        (
            strips(&dir, "gap", 1.0, Shape::Gap(0.06)),
            Resolution::Patches(100),
        ),
    ];
    let mut failures = Vec::new();
    for (scene, res) in &scenes {
        let patches = PatchSet::build(&Scene::load(scene).expect("scene"), *res).expect("mesh");
        // Exact rows: the semi-analytic integral to 1e-9 (nothing blocks in these scenes).
        let exact = pipeline::form_factors(
            &patches,
            &EstimatorChoice::SemiAnalytic {
                points: 3,
                rays: 2,
                replicates: 4,
                tol: 1e-9,
            },
            1,
            &Quiet,
        )
        .expect("exact factors")
        .0;
        for est in defaults() {
            let (ff, _, _) =
                pipeline::form_factors(&patches, &est, 1, &Quiet).expect("form factors");
            // Rows within 3 of their bars of the exact rows (t with 3 degrees of freedom for
            // 4 replicates: 94.2% of honest rows are; bounds count once, and the reference's
            // own bound is added).
            let n = ff.len();
            let covered = (0..n)
                .filter(|&i| {
                    let err = (ff.row_sum(i) - exact.row_sum(i)).abs();
                    err <= ff.row_sum_bar(i).allowance(3.0) + exact.row_sum_bar(i).bound
                })
                .count() as f64
                / n as f64;
            let over = rows_over(&ff, 3.0);
            let beyond = ff.row_over_one_beyond_chance();
            let worst = (0..ff.len())
                .map(|i| (ff.row_sum(i), ff.row_sum_bar(i)))
                .fold((0.0, Bar::ZERO), |w, r| if r.0 > w.0 { r } else { w });
            eprintln!(
                "{scene} {res:?} {}: largest row {:.4} {}, {} rows over 1 beyond 3 bars, \
                 beyond chance: {:?}, rows within 3 bars of exact {:.1}%",
                ff.estimator,
                worst.0,
                worst.1,
                over.len(),
                beyond,
                100.0 * covered
            );
            // Four checks: no row over 1 beyond chance (the project's rule, a family-wise
            // rate of 1e-3 per matrix); none over 1 by more than 3 of its bars either (with
            // near pairs integrated to a bound the rows' random part is small against their
            // distance from 1: none in 20 seeds on these scenes, where pairs within a
            // quarter side sampled at random nodes put 1 to 2 rows of 1000 over); rows bounded (without the near-pair integral rows
            // reached 2.4 to 11.9 here, with bars as wide); and bars that cover: honest
            // rows are within 3 bars 94.2% of the time, and of 100 rows fewer than 85% is
            // 4 binomial deviations off (false alarm about 3e-5 per case; without the
            // near-pair integral 70% to 83% on the 100-patch meshes).
            if let Some(x) = beyond {
                failures.push(format!("{scene} {res:?} {}: {x:?}", ff.estimator));
            }
            if !over.is_empty() {
                failures.push(format!(
                    "{scene} {res:?} {}: over 1 by 3 bars: {over:?}",
                    ff.estimator
                ));
            }
            if worst.0 > 1.5 {
                failures.push(format!("{scene} {res:?} {}: row {worst:?}", ff.estimator));
            }
            if covered < 0.85 {
                failures.push(format!(
                    "{scene} {res:?} {}: {:.1}% of rows within 3 bars of exact",
                    ff.estimator,
                    100.0 * covered
                ));
            }
        }
    }
    std::fs::remove_dir_all(&dir).ok();
    assert!(failures.is_empty(), "{failures:#?}");
}

/// The near test: patches that share an edge are near, patches farther apart than
/// [`NEAR`] times the larger one's side are not, whatever the mesh.
#[test]
fn near_pairs_are_those_closer_than_the_larger_side() {
    let dir = std::env::temp_dir().join(format!("radiosity-near-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    for (gap, want) in [
        (0.0, true),
        (0.5, true),
        (1.99, true),
        (2.01, false),
        (4.0, false),
    ] {
        // Two 4 x 1 strips (one patch each, side √4 = 2, reach 2) facing each other
        // `gap` apart, or unit squares sharing an edge at a right angle for gap 0.
        let scene = if gap == 0.0 {
            Scene::load("plates-perpendicular").expect("built in")
        } else {
            Scene::load(&strips(&dir, "pair", 1.0, Shape::Gap(gap))).expect("scene")
        };
        let p = PatchSet::build(&scene, Resolution::MaxEdge(10.0)).expect("mesh");
        let (a, b) = (p.corner_points(0), p.corner_points(1));
        let got = near(&p, (0, &a.0[..a.1]), (1, &b.0[..b.1]));
        assert_eq!(got, want, "gap {gap} (reach {NEAR} x side)");
    }
    std::fs::remove_dir_all(&dir).ok();
}
