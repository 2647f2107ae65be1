//! Form factors against closed forms (Howell's catalogue), closure and reciprocity.

use radiosity::formfactor::{compute, AreaMc, Context, Pattern};
use radiosity::matrix::FormFactors;
use radiosity::mesh::{PatchSet, Resolution};
use radiosity::pipeline::{self, BakeConfig, EstimatorChoice, Quiet};
use radiosity::scene::Scene;
use radiosity::visibility::Visibility;

/// Howell C-14, unit squares with a common edge.
const F_PERPENDICULAR: f64 = 0.200_043_776_075_403_16;
/// Howell C-11, opposed unit squares at distance 1.
const F_PARALLEL: f64 = 0.199_824_895_698_387_5;

fn factors(
    scene: &str,
    res: Resolution,
    est: &EstimatorChoice,
    seed: u64,
) -> (PatchSet, FormFactors) {
    let scene = Scene::load(scene).expect("built-in scene");
    let patches = PatchSet::build(&scene, res).expect("patches");
    let (ff, _, _) = pipeline::form_factors(&patches, est, seed, &Quiet).expect("form factors");
    (patches, ff)
}

/// Each estimate within 3 of its own standard errors of the closed form, or within its
/// bound where its error is deterministic (the default semi-analytic estimator on these
/// unoccluded pairs: a bound that must hold, no false alarm). Two random checks at 3
/// sigma: a false alarm has probability about 0.5% under normality.
#[test]
fn plates_match_howell_within_three_standard_errors() {
    // (estimator, largest useful relative error bar): point pairs on patches with a shared
    // edge have an unbounded kernel, so the area estimator's bar stays wide there.
    let estimators = [
        (
            EstimatorChoice::AreaStratified {
                strata: 64,
                replicates: 16,
            },
            0.05,
        ),
        (BakeConfig::default().estimator, 0.01),
    ];
    for (est, useful) in &estimators {
        for (scene, exact) in [
            ("plates-perpendicular", F_PERPENDICULAR),
            ("plates-parallel", F_PARALLEL),
        ] {
            let (_, ff) = factors(scene, Resolution::MaxEdge(10.0), est, 7);
            let (f, bar) = (ff.get(0, 1), ff.bar(0, 1));
            let se = bar.magnitude();
            eprintln!(
                "{scene} {}: F = {f:.7} {bar} (exact {exact}, error {:.1e})",
                ff.estimator,
                f - exact
            );
            assert!(se > 0.0 && bar.is_valid(), "{scene}: bar {bar}");
            assert!(
                (f - exact).abs() <= bar.allowance(3.0),
                "{scene} {}: |{f} - {exact}| beyond 3 × {bar}",
                ff.estimator
            );
            assert!(
                se < useful * exact,
                "{scene} {}: error bar {se} too wide to be useful",
                ff.estimator
            );
        }
    }
}

/// Hemisphere shooting with strata counts that are not powers of 2 (the hashed pairing
/// then walks cycles) and 1 (no stratification, one ray per replicate), on both plates:
/// each estimate within 3.5 of its standard errors of the closed form, with a bar under 5%
/// of the value. With 16 replicates the statistic is a t with 15 degrees of freedom,
/// P(|t| > 3.5) = 0.3%: six checks, a false alarm for about 2% of seeds.
#[test]
fn hemisphere_with_odd_strata_matches_howell() {
    for (strata, replicates) in [(1, 4096), (13, 16), (23, 16)] {
        let est = EstimatorChoice::Hemisphere { strata, replicates };
        for (scene, exact) in [
            ("plates-perpendicular", F_PERPENDICULAR),
            ("plates-parallel", F_PARALLEL),
        ] {
            let (_, ff) = factors(scene, Resolution::MaxEdge(10.0), &est, 11);
            let (f, se) = (ff.get(0, 1), ff.stderr(0, 1));
            eprintln!(
                "{scene} {}: F = {f:.5} ± {se:.1e} (exact {exact:.5})",
                ff.estimator
            );
            assert!(se > 0.0 && se.is_finite(), "{scene}: standard error {se}");
            assert!(
                (f - exact).abs() <= 3.5 * se,
                "{scene} {}: |{f} - {exact}| > 3.5 × {se}",
                ff.estimator
            );
            assert!(se < 0.05 * exact, "{scene} {}: bar {se}", ff.estimator);
        }
    }
}

/// In the closed cube every row sums to 1 and A_i F_ij = A_j F_ji, at the default
/// estimator and sample count.
#[test]
fn closed_cube_rows_sum_to_one_and_reciprocity_holds() {
    let est = BakeConfig::default().estimator;
    let (patches, ff) = factors("cube", Resolution::MaxEdge(0.25), &est, 3);
    assert_eq!(patches.len(), 96);
    let d = ff.diagnostics();
    eprintln!(
        "cube: row sums in [{}, {}], reciprocity {:.2e}",
        d.min_row_sum, d.max_row_sum, d.reciprocity
    );
    // The default (semi-analytic) estimator integrates each factor to 1e-6 relative and,
    // with nothing to block in the cube, casts no ray: the rows reach 1 to about 1e-8.
    for i in 0..ff.len() {
        let s = ff.row_sum(i);
        assert!((s - 1.0).abs() <= 1e-7, "row {i} sums to {s}");
    }
    // It computes each pair once and fills its mirror by reciprocity.
    assert!(
        d.reciprocity <= 1e-12,
        "reciprocity error {}",
        d.reciprocity
    );
    assert_eq!(d.out_of_range, 0);
}

/// The semi-analytic estimator on the closed cube with 8 x 8 patches per face (384
/// patches, every pair unoccluded, so no rays): the face-to-face factors, aggregated from
/// the patch matrix by area, match the closed forms (C-14 for adjacent faces, C-11 for
/// opposite ones) within 1e-9, and each within its own error bar (the area-weighted sum
/// of the entries' quadrature error estimates), which must itself be small.
#[test]
fn cube_face_to_face_factors_to_1e9() {
    let est = EstimatorChoice::SemiAnalytic {
        points: 3,
        rays: 2,
        replicates: 2,
        tol: 1e-9,
    };
    let (patches, ff) = factors("cube", Resolution::MaxEdge(0.125), &est, 1);
    assert_eq!(patches.len(), 384);
    assert_eq!(ff.rays, 0, "a convex room needs no visibility rays");
    let face = |n: glam::DVec3| -> usize {
        let a = n.abs();
        let k = if a.x >= a.y && a.x >= a.z {
            0
        } else if a.y >= a.z {
            1
        } else {
            2
        };
        2 * k + usize::from(n[k] > 0.0)
    };
    let mut sum = [[0.0f64; 6]; 6];
    let mut bar = [[0.0f64; 6]; 6];
    let mut area = [0.0f64; 6];
    for i in 0..patches.len() {
        let fi = face(patches.normal[i]);
        area[fi] += patches.area[i];
        for (j, f, se) in ff.row(i) {
            let fj = face(patches.normal[j]);
            sum[fi][fj] += patches.area[i] * f;
            bar[fi][fj] += patches.area[i] * se.magnitude();
        }
    }
    let mut worst = 0.0f64;
    for a in 0..6 {
        for b in 0..6 {
            if a == b {
                continue;
            }
            let exact = if a / 2 == b / 2 {
                F_PARALLEL
            } else {
                F_PERPENDICULAR
            };
            let (got, err) = (sum[a][b] / area[a], bar[a][b] / area[a]);
            let off = (got - exact).abs();
            worst = worst.max(off);
            assert!(off <= 1e-9, "faces {a}->{b}: {got} vs {exact}");
            assert!(
                off <= err.max(1e-14),
                "faces {a}->{b}: error {off:e} beyond its bar {err:e}"
            );
            assert!(err <= 1e-8, "faces {a}->{b}: bar {err:e} too wide");
        }
    }
    eprintln!("cube 8x8 face-to-face: worst error {worst:.2e}");
}

/// The area estimator with few samples on adjacent patches is noisy, and says so: its row
/// sums miss 1, but by amounts its own standard errors account for.
#[test]
fn noisy_rows_come_with_honest_error_bars() {
    let est = EstimatorChoice::AreaStratified {
        strata: 4,
        replicates: 8,
    };
    let (_, ff) = factors("cube", Resolution::MaxEdge(0.5), &est, 11);
    let mut outside = 0;
    for i in 0..ff.len() {
        let (s, bar) = (ff.row_sum(i), ff.row_sum_bar(i));
        assert!(s.is_finite() && bar.is_valid());
        if (s - 1.0).abs() > bar.allowance(4.0) {
            outside += 1;
        }
    }
    // 24 rows at 4 sigma: heavy tails allow a couple, not most.
    assert!(
        outside <= 3,
        "{outside} of 24 row sums are more than 4 standard errors from 1"
    );
}

#[test]
fn results_do_not_depend_on_thread_count() {
    let scene = Scene::load("cornell").expect("built-in scene");
    let patches = PatchSet::build(&scene, Resolution::Patches(150)).expect("patches");
    let vis = Visibility::new(&patches).expect("embree");
    let ctx = Context {
        patches: &patches,
        vis: &vis,
        seed: 5,
    };
    let run = |threads: usize, est: &dyn radiosity::formfactor::Estimator| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool");
        pool.install(|| compute(&ctx, est, &|_| {}))
    };
    let area = AreaMc::new(Pattern::Stratified, 3, 2);
    let semi = BakeConfig::default().estimator.build();
    for est in [
        &area as &dyn radiosity::formfactor::Estimator,
        semi.as_ref(),
    ] {
        let (a, b) = (run(1, est), run(2, est));
        assert_eq!(a.f, b.f, "{}", a.estimator);
        assert_eq!(a.se, b.se, "{}", a.estimator);
        assert_eq!(a.rays, b.rays);
    }
}

/// The sampling passes compiled for AVX-512, for AVX2 and at the baseline width give the same bits
/// (`radiosity::simd`: no fused multiply-adds, the same operations in the same order), for
/// every estimator with such passes, on a scene with triangles and quads, and with an odd
/// sample count (a partial last packet of segment rays).
#[test]
fn vector_width_does_not_change_results() {
    let scene = Scene::load("cornell").expect("built-in scene");
    let patches = PatchSet::build(&scene, Resolution::Patches(120)).expect("patches");
    let vis = Visibility::new(&patches).expect("embree");
    let ctx = Context {
        patches: &patches,
        vis: &vis,
        seed: 9,
    };
    let choices = [
        EstimatorChoice::AreaStratified {
            strata: 4,
            replicates: 3,
        },
        EstimatorChoice::AreaUniform {
            strata: 3,
            replicates: 3,
        },
        EstimatorChoice::Hemisphere {
            strata: 7,
            replicates: 3,
        },
        // Unoccluded pairs by Gauss rules whose point factors are evaluated in lanes,
        // occluded ones sampled.
        EstimatorChoice::SemiAnalytic {
            points: 3,
            rays: 2,
            replicates: 3,
            tol: 1e-6,
        },
    ];
    for choice in &choices {
        let est = choice.build();
        use radiosity::simd::{set_limit, Width};
        set_limit(Width::Baseline);
        let narrow = compute(&ctx, est.as_ref(), &|_| {});
        assert!(narrow.f.nnz() > 0);
        for w in [Width::Avx2, Width::Avx512] {
            set_limit(w);
            let wide = compute(&ctx, est.as_ref(), &|_| {});
            let name = format!("{} at {w}", narrow.estimator);
            assert_eq!(narrow.f, wide.f, "{name}");
            assert_eq!(narrow.se, wide.se, "{name}");
            assert_eq!(narrow.rays, wide.rays);
        }
    }
}
