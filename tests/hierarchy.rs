//! Hierarchical radiosity against closed forms: closure and the furnace, the notes' shelf,
//! crack-free output, determinism, and refinement where visibility changes.

use radiosity::hierarchy::{self, Clustering, Settings, Solution};
use radiosity::mesh::{PatchSet, Resolution};
use radiosity::scene::Scene;
use radiosity::visibility::Visibility;

fn solve(scene: &str, res: Resolution, s: &Settings) -> (PatchSet, Solution) {
    let scene = Scene::load(scene).expect("scene");
    let patches = PatchSet::build(&scene, res).expect("patches");
    let vis = Visibility::new(&patches).expect("bvh");
    let sol = hierarchy::run(&patches, &vis, s, &|_| {}).expect("hierarchy");
    (patches, sol)
}

#[test]
fn closed_cube_links_sum_to_one_and_the_furnace_holds() {
    let s = Settings {
        error: 0.02,
        min_area: Some(1.0 / 256.0),
        quadrature: 1e-10,
        accuracy: 0.0,
        tolerance: 1e-10,
        ..Settings::default()
    };
    let (_, sol) = solve("cube", Resolution::Patches(6), &s);
    // Refined (so the test is not of the roots alone), every leaf's factors sum to 1.
    assert!(sol.elements.len() > 1000);
    let r = &sol.report;
    assert!(
        (r.max_row_sum.0 - 1.0).abs() < 1e-8,
        "largest factor sum {:?}",
        r.max_row_sum
    );
    for l in sol.elements.leaves() {
        for c in sol.state.b[l as usize] {
            assert!((c - 2.0).abs() < 1e-6, "leaf {l}: B = {c}");
        }
    }
    for c in 0..3 {
        let rel = (r.emitted[c] - r.absorbed[c]).abs() / r.emitted[c];
        assert!(rel < 1e-6, "power balance {rel:e}");
    }
}

/// Memory: an unclustered hierarchy (`--clusters off`) whose links between every pair of
/// roots would not fit is refused before any link is evaluated, naming what would fit
/// (`--clusters auto`, the default, clusters it instead); within a small limit
/// the refinement stops at the links that fit, with a note, and still solves.
#[test]
fn the_memory_limit_refuses_or_caps_the_links() {
    let scene = Scene::load("scenes/room-sphere.obj").expect("scene");
    let patches = PatchSet::build(&scene, Resolution::DiagonalFraction(0.25)).expect("patches");
    let vis = Visibility::new(&patches).expect("bvh");
    let s = Settings {
        max_memory: Some(64 << 20),
        clusters: Clustering::Off,
        ..Settings::default()
    };
    let e = hierarchy::run(&patches, &vis, &s, &|_| {})
        .err()
        .expect("refused")
        .to_string();
    assert!(
        e.contains("root patches")
            && e.contains("--clusters on")
            && e.contains("--max-memory")
            && e.contains(&format!("{} root patches", patches.len())),
        "{e}"
    );

    // The cube: 30 initial links fit; a limit of about 3,000 links (with their share of
    // the final gather) stops the refinement.
    let limit = 3_000 * radiosity::hierarchy::MEMORY_PER_LINK;
    let s = Settings {
        error: 0.02,
        min_area: Some(1.0 / 4096.0),
        max_memory: Some(limit),
        ..Settings::default()
    };
    let (_, sol) = solve("cube", Resolution::Patches(6), &s);
    let r = &sol.report;
    assert!(
        r.notes
            .iter()
            .any(|n| n.contains("set by the memory limit")),
        "notes {:?}",
        r.notes
    );
    assert!(r.links <= 3_000, "links {}", r.links);
    // Unlimited, the same bake makes more links than the cap.
    let (_, free) = solve(
        "cube",
        Resolution::Patches(6),
        &Settings {
            max_memory: None,
            ..s
        },
    );
    assert!(free.report.links > 3_000, "links {}", free.report.links);
}

/// Every edge of the output mesh of a watertight input, by position, is shared by exactly
/// two triangles: no T-vertex cracks.
#[test]
fn watertight_input_gives_a_watertight_mesh() {
    let s = Settings {
        error: 0.02,
        min_area: Some(1.0 / 1024.0),
        ..Settings::default()
    };
    let (patches, sol) = solve("cube", Resolution::Patches(6), &s);
    // The hierarchy is not uniform (else the test proves nothing).
    let levels: std::collections::BTreeSet<u8> = sol
        .elements
        .leaves()
        .map(|l| sol.elements.level[l as usize])
        .collect();
    assert!(levels.len() >= 3, "levels {levels:?}");
    let (mesh, _, _) = hierarchy::leaves::leaf_mesh(&sol.elements, &patches, &sol.state.b);
    let key = |k: u32| {
        let p = mesh.vertices[k as usize];
        [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()]
    };
    let mut edges: std::collections::HashMap<([u64; 3], [u64; 3]), u32> =
        std::collections::HashMap::new();
    for t in &mesh.triangles {
        for k in 0..3 {
            let (a, b) = (key(t[k]), key(t[(k + 1) % 3]));
            *edges.entry((a.min(b), a.max(b))).or_default() += 1;
        }
    }
    let bad: Vec<_> = edges.iter().filter(|(_, &n)| n != 2).collect();
    assert!(
        bad.is_empty(),
        "{} of {} edges not shared by two triangles",
        bad.len(),
        edges.len()
    );
    // And the leaves tile the roots: children's areas sum to their parents'.
    let e = &sol.elements;
    for p in 0..e.len() as u32 {
        if !e.is_leaf(p) {
            let s: f64 = e.children(p).iter().map(|&c| e.area[c as usize]).sum();
            assert!((s - e.area[p as usize]).abs() <= 1e-12 * e.area[p as usize]);
        }
    }
}

/// Settings that hold the hierarchy's refinement at the roots (the notes' table is for one
/// constant value across each strip).
fn shelf_settings() -> Settings {
    Settings {
        min_area: Some(1e9),
        tolerance: 1e-12,
        ..Settings::default()
    }
}

/// The notes' infinite shelf, as in `shelf.rs`, solved on the hierarchy with refinement
/// held at the roots: the middle slice reproduces the table.
#[test]
fn shelf_table_on_the_hierarchy() {
    let rows = shelf_rows(&shelf_settings()).1;
    let table: Vec<[f64; 3]> = crate::shelf::TABLE.iter().map(|r| r.2).collect();
    assert_rows_within(&rows, &table, 1e-4, "the notes give");
}

/// Each shelf's middle radiosity in `got` within `tol` of `want`, row by row.
fn assert_rows_within(got: &[[f64; 3]], want: &[[f64; 3]], tol: f64, against: &str) {
    for (row, (got, want)) in got.iter().zip(want).enumerate() {
        for (k, name) in ["A", "B", "C"].iter().enumerate() {
            assert!(
                (got[k] - want[k]).abs() <= tol,
                "row {}: B_{name} = {:.6}, {against} {:.6}",
                row + 1,
                got[k],
                want[k]
            );
        }
    }
}

/// The notes' shelf with clusters on, the cluster transfers integrated to 1e-8 and the
/// link tolerance at 0.003: distant parts of the shelves exchange light through cluster
/// links (282 to 342 a row, measured), and the middle slice stays within 3e-5 of the same
/// shelf solved without clusters (measured: worst 1.8e-5, row 4's `B_C`, 0.328418 against
/// 0.328436; at the default tolerance 0.01 the worst is 3.2e-5, row 4's `B_B`). The
/// comparison is with the unclustered solution rather than the table because the finite
/// shelf itself sits 9.4e-5 below the table's row 4 `B_C` (0.32853), which leaves a table
/// check at 1e-4 no room to tell a cluster's error from the shelf's length.
#[test]
fn shelf_table_with_clusters() {
    let (_, plain) = shelf_rows(&shelf_settings());
    let (cluster_links, got) = shelf_rows(&Settings {
        clusters: Clustering::On,
        cluster_quadrature: 1e-8,
        error: 0.003,
        ..shelf_settings()
    });
    eprintln!("cluster links per row: {cluster_links:?}");
    assert!(cluster_links.iter().all(|&n| n > 0), "{cluster_links:?}");
    assert_rows_within(&got, &plain, 3e-5, "with clusters; without");
}

/// Bakes every row of the notes' shelf table with settings `s` (no element split);
/// returns each row's cluster links and the radiosity (red) of the middle patch of each
/// shelf, A, B and C.
fn shelf_rows(s: &Settings) -> (Vec<usize>, Vec<[f64; 3]>) {
    let (mut cluster_links, mut rows) = (Vec::new(), Vec::new());
    let mut scene = Scene::load("shelf").expect("shelf");
    let (lo, hi) = scene.bounds();
    let mid_x = 0.5 * (lo.x + hi.x);
    for (rho, emit, _) in crate::shelf::TABLE.iter() {
        for (k, name) in ["A", "B", "C"].iter().enumerate() {
            scene
                .set_material(name, [rho[k]; 3], [emit[k]; 3])
                .expect("material");
        }
        let patches = PatchSet::build(&scene, Resolution::MaxEdge(2.0)).expect("patches");
        let vis = Visibility::new(&patches).expect("bvh");
        let sol = hierarchy::run(&patches, &vis, s, &|_| {}).expect("hierarchy");
        assert_eq!(sol.elements.len(), patches.len(), "nothing was split");
        cluster_links.push(sol.report.cluster_links);
        let mut row = [0.0; 3];
        for (k, name) in ["A", "B", "C"].iter().enumerate() {
            let m = scene.material_index(name).expect("material") as u32;
            let mid = (0..patches.len())
                .filter(|&i| patches.material[i] == m)
                .min_by(|&a, &b| {
                    let da = (patches.centroid[a].x - mid_x).abs();
                    let db = (patches.centroid[b].x - mid_x).abs();
                    da.total_cmp(&db)
                })
                .expect("patch");
            row[k] = sol.state.b[mid][0];
        }
        rows.push(row);
    }
    (cluster_links, rows)
}

/// The same seed gives the same hierarchy and the same bits on 1 and 2 threads, with and
/// without clusters.
#[test]
fn same_bits_on_any_thread_count() {
    for clusters in [Clustering::Off, Clustering::On] {
        let s = Settings {
            error: 0.04,
            clusters,
            ..Settings::default()
        };
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("pool");
            pool.install(|| solve("cornell", Resolution::DiagonalFraction(0.5), &s).1)
        };
        let (a, b) = (run(1), run(2));
        assert_eq!(a.elements.len(), b.elements.len(), "clusters {clusters:?}");
        assert_eq!(a.report.links, b.report.links, "clusters {clusters:?}");
        assert_eq!(a.report.rays, b.report.rays, "clusters {clusters:?}");
        for (x, y) in a.state.b.iter().zip(&b.state.b) {
            assert_eq!(
                x.map(f64::to_bits),
                y.map(f64::to_bits),
                "clusters {clusters:?}"
            );
        }
    }
}

/// Partial visibility and contacts refine: next to the short block's base the floor's
/// leaves are at the minimum size, partly visible links exist, and leaves far from any
/// shadow stay large; a tolerance nothing exceeds splits nothing but contacts.
#[test]
fn shadows_and_contacts_refine_and_refinement_stops_at_the_tolerance() {
    let s = Settings::default();
    let (_, sol) = solve("cornell", Resolution::DiagonalFraction(0.25), &s);
    let e = &sol.elements;
    let min_area = sol.report.min_area;
    assert!(sol.report.partial_links > 0);
    assert!(sol.report.buried > 0, "floor under the blocks is buried");
    // No leaf gathers more than all it sees: the largest factor sum within 5 of its bars
    // (5: a one-sided tail of 3e-7 per leaf, 1% over the ~25,000 leaves). Leaves beside
    // a block once inherited their parent's view of the wall behind it and reached 1.05,
    // 12 bars over.
    let (sum, bar) = sol.report.max_row_sum;
    assert!(
        sum <= 1.0 + bar.allowance(5.0),
        "largest leaf factor sum {sum} ± {bar}"
    );
    // The largest sum is often the noisiest leaf's (a partly buried leaf's bar includes the
    // error of the exposed fraction its factors are divided by), so the bars are checked
    // over all leaves: with calibrated bars and no bias, a one-sided 3-bar excess has
    // probability 0.13%; at most 0.2% of the leaves may show it. (A leaf's check of a
    // source is its own 4 rays' estimate, unbiased and noisier than 16 rays': the largest
    // sum's bar is about 0.11 here.)
    assert!(bar.magnitude() < 0.15, "bar {bar}");
    let over = sol.report.rows_over_one;
    assert!(
        over * 500 <= sol.report.leaves,
        "{over} of {} leaves over 1 beyond 3 bars",
        sol.report.leaves
    );
    // Floor leaves (normal +y, y = 0) within 3 mm of the short block's edge from
    // (130, 65) to (290, 114), outside the block, are at the minimum size.
    let (a, b) = (
        glam::DVec2::new(130.0, 65.0),
        glam::DVec2::new(290.0, 114.0),
    );
    let mut near = 0;
    for l in e.leaves() {
        let li = l as usize;
        let c = e.centre[li];
        if e.normal[li].y < 0.99 || c.y.abs() > 1e-6 {
            continue;
        }
        let p = glam::DVec2::new(c.x, c.z);
        let t = ((p - a).dot(b - a) / (b - a).length_squared()).clamp(0.0, 1.0);
        if (p - (a + (b - a) * t)).length() < 3.0 {
            near += 1;
            assert!(
                e.area[li] / 4.0 < min_area,
                "leaf {l} at {c} has area {}",
                e.area[li]
            );
        }
    }
    assert!(near > 10);
    let largest = e.leaves().map(|l| e.area[l as usize]).fold(0.0, f64::max);
    assert!(largest > 1000.0 * min_area);
    // A tolerance no link exceeds: only the contact splits remain.
    let loose = Settings {
        error: 1e6,
        ..Settings::default()
    };
    let (_, sol2) = solve("cornell", Resolution::DiagonalFraction(0.25), &loose);
    assert_eq!(
        sol2.report.passes.iter().map(|p| p.refined).sum::<usize>(),
        0
    );
    assert_eq!(
        sol2.elements.len(),
        sol2.report.roots + 4 * sol2.report.contact_splits
    );
}

/// Mean luminance over the visible area of the leaves under each root, and under each
/// object. A partly buried leaf counts its exposed part only (`Elements::visible_area`):
/// its radiosity is that part's, and weighting its whole area made a bake that splits
/// such leaves more finely (the ceiling around `room-spheres-2`'s light, whose middle is
/// hidden 1 cm above it) differ by 0.6% in the ceiling's mean where, over the visible
/// area, it differs by 0.06%.
fn averages(patches: &PatchSet, sol: &Solution) -> (Vec<f64>, Vec<f64>) {
    use radiosity::scene::luminance;
    let e = &sol.elements;
    let n_obj = patches.objects.len().max(1);
    let (mut root, mut root_a) = (vec![0.0; e.roots], vec![0.0; e.roots]);
    for l in e.leaves() {
        let li = l as usize;
        if e.buried[li] {
            continue;
        }
        let r = e.root[li] as usize;
        let a = e.visible_area(l);
        root[r] += a * luminance(sol.state.b[li]);
        root_a[r] += a;
    }
    let (mut obj, mut obj_a) = (vec![0.0; n_obj], vec![0.0; n_obj]);
    for r in 0..e.roots {
        let o = patches.object[r] as usize;
        obj[o] += root[r];
        obj_a[o] += root_a[r];
    }
    let mean = |s: Vec<f64>, a: Vec<f64>| -> Vec<f64> {
        s.iter()
            .zip(&a)
            .map(|(s, a)| if *a > 0.0 { s / a } else { 0.0 })
            .collect()
    };
    (mean(root, root_a), mean(obj, obj_a))
}

#[test]
fn clustered_and_unclustered_bakes_agree() {
    // Cluster links on roots only (`--split-receivers off`): the receivers split below
    // them count as initial links too, which the ratio below is about (with them: objects
    // within 0.12%, roots 1.34%, 4.3x fewer initial links).
    let base = Settings {
        error: 0.02,
        split_receivers: false,
        ..Default::default()
    };
    let on = Settings {
        clusters: Clustering::On,
        ..base.clone()
    };
    let off = Settings {
        clusters: Clustering::Off,
        ..base
    };
    let res = Resolution::DiagonalFraction(0.25);
    let (p, a) = solve("room-spheres-2", res, &on);
    let (_, b) = solve("room-spheres-2", res, &off);
    // With cluster links held to a relative bound of 3: closer, fewer savings.
    let tight = Settings {
        cluster_accuracy: 3.0,
        ..on.clone()
    };
    let (_, c) = solve("room-spheres-2", res, &tight);
    let (_, oc) = averages(&p, &c);
    let worst_tight = oc
        .iter()
        .zip(&averages(&p, &b).1)
        .map(|(x, y)| (x / y - 1.0).abs())
        .fold(0.0, f64::max);
    eprintln!(
        "accuracy 3: objects worst {worst_tight:.4}, initial links {}",
        c.report.initial_links
    );
    for (k, (x, y)) in oc.iter().zip(&averages(&p, &b).1).enumerate() {
        eprintln!(
            "  {}: {x:.5} vs {y:.5} ({:+.3}%)",
            p.objects[k],
            100.0 * (x / y - 1.0)
        );
    }
    let (ra, oa) = averages(&p, &a);
    let (rb, ob) = averages(&p, &b);
    let worst_obj = oa
        .iter()
        .zip(&ob)
        .map(|(x, y)| (x / y - 1.0).abs())
        .fold(0.0, f64::max);
    // Roots of the spheres: small triangles, as points.
    let mut worst_root = 0.0f64;
    let mut over = 0;
    for r in 0..ra.len() {
        if rb[r] > 0.0 {
            let d = (ra[r] / rb[r] - 1.0).abs();
            worst_root = worst_root.max(d);
            over += usize::from(d > 0.03);
        }
    }
    let (ia, ib) = (a.report.initial_links, b.report.initial_links);
    eprintln!(
        "objects worst {worst_obj:.4}; roots worst {worst_root:.4}, {over} of {} over 3%; \
         initial links {ia} vs {ib}; links {} vs {}; cluster links {}",
        ra.len(),
        a.report.links,
        b.report.links,
        a.report.cluster_links
    );
    for (k, (x, y)) in oa.iter().zip(&ob).enumerate() {
        eprintln!(
            "  {}: {x:.5} vs {y:.5} ({:+.3}%)",
            p.objects[k],
            100.0 * (x / y - 1.0)
        );
    }
    eprintln!(
        "  power on {:?} {:?}, off {:?} {:?}; rows over one {} vs {}",
        a.report.emitted,
        a.report.absorbed,
        b.report.emitted,
        b.report.absorbed,
        a.report.rows_over_one,
        b.report.rows_over_one
    );
    // Measured: objects within 0.10%, roots within 0.59%, 5.9x fewer initial links
    // (docs/HIERARCHY.md, Clustering); with `split_receivers` 0.12%, 1.34%, 4.3x. With
    // the point source alone: 1.4% (every object darker) and 1.8%.
    assert!(
        worst_tight < 0.0015,
        "objects differ by {worst_tight} at accuracy 3"
    );
    assert!(c.report.initial_links * 4 < b.report.initial_links);
    assert!(a.report.cluster_links > 0);
    assert!(worst_obj < 0.005, "object averages differ by {worst_obj}");
    assert!(worst_root < 0.015, "root averages differ by {worst_root}");
    assert!(ia * 5 < ib, "initial links {ia} vs {ib}");
}

/// The closed cube cut into 16 x 16 patches a face, far enough apart for cluster links
/// between groups of patches; rho 0.5 and E 1 everywhere: B = 2. Returns the report and
/// the area-weighted mean B, the worst leaf's relative error and the share of the power
/// unaccounted for.
fn cube_furnace_with_clusters(accuracy: f64) -> (hierarchy::Report, f64, f64, f64) {
    let s = Settings {
        error: 0.02,
        min_area: Some(1.0 / 1024.0),
        clusters: Clustering::On,
        cluster_accuracy: accuracy,
        ..Settings::default()
    };
    let (_, sol) = solve("cube", Resolution::Patches(1536), &s);
    let r = sol.report;
    let e = &sol.elements;
    let (mut worst, mut sum, mut area) = (0.0f64, 0.0, 0.0);
    for l in e.leaves() {
        let b = sol.state.b[l as usize][0];
        worst = worst.max((b - 2.0).abs() / 2.0);
        sum += e.area[l as usize] * b;
        area += e.area[l as usize];
    }
    let mean = sum / area;
    let balance = (r.emitted[0] - r.absorbed[0]).abs() / r.emitted[0];
    eprintln!(
        "cube furnace with clusters, accuracy {accuracy}: {} cluster links, {} initial links, \
         mean B {mean:.6}, worst leaf {worst:.4}, power {balance:.2e}, largest factor sum {:?}",
        r.cluster_links, r.initial_links, r.max_row_sum
    );
    (r, mean, worst, balance)
}

#[test]
fn furnace_with_clusters() {
    let (r, mean, worst, balance) = cube_furnace_with_clusters(f64::INFINITY);
    // Measured: mean B -6.5e-5, worst leaf 0.18%, 1.3e-4 of the power unaccounted for,
    // largest factor sum 1.0031 ± 0.0036 (without clusters: 1e-6). With the point source
    // alone (no near-field correction), whose errors have one sign and add up over a
    // receiver's links: +1.2%, 6.9%, 2.4% and 1.115.
    assert!(r.cluster_links > 0);
    assert!((mean - 2.0).abs() / 2.0 < 1e-3, "mean B {mean}");
    assert!(worst < 0.01, "worst leaf {worst}");
    assert!(balance < 1e-3, "power balance {balance:e}");
    assert!(
        r.max_row_sum.0 < 1.02,
        "largest factor sum {:?}",
        r.max_row_sum
    );
}

/// The rows of docs/HIERARCHY.md's cube furnace table at the cluster accuracies it lists
/// (`cargo test --release --test tests furnace_with_clusters_by_accuracy -- --ignored
/// --nocapture`).
#[test]
#[ignore]
fn furnace_with_clusters_by_accuracy() {
    for accuracy in [f64::INFINITY, 4.0, 2.0, 1.0, 0.5] {
        cube_furnace_with_clusters(accuracy);
    }
}

/// The Cornell box closed by a front wall, every face ρ 0.5 and E 1: B = 2 everywhere
/// (`scenes/cornell-furnace.obj`), at default settings. What a bake loses here is one-sided
/// (links and gather entries that miss light), so the mean radiosity and the power balance
/// measure it. Measured: mean 2.0000, 2.3e-5 of the power unaccounted for, since links
/// whose rays were all blocked go to Russian roulette instead of being dropped (before:
/// 1.9988 and 1.2e-3, which the bounds of 5e-4 below refuse; 1.9982 and 0.18% before
/// receivers were split for their shadows; 1.9959 and 0.41% before partly buried leaves
/// were measured and the refinement decided on unoccluded factors).
#[test]
fn cornell_furnace_keeps_its_light() {
    let (_, sol) = solve(
        "scenes/cornell-furnace.obj",
        Resolution::DiagonalFraction(0.25),
        &Settings::default(),
    );
    let r = &sol.report;
    let mean = r.mean_radiosity;
    assert!((mean - 2.0).abs() < 5e-4, "mean radiosity {mean}");
    let lost = (r.emitted[0] - r.absorbed[0]) / r.emitted[0];
    assert!(lost.abs() < 5e-4, "power unaccounted for {lost:e}");
    // The estimated error per leaf against the actual `|B - 2|` (docs/HIERARCHY.md, *The
    // error estimate*): measured, the estimate's mean is 5.58 times the actual mean, and
    // the actual error is above the estimate on 0.55% of the visible area (5.18 and 0.7%
    // before the roulette, whose entries widen the bars). Before receivers
    // were split for their shadows: 4.3 times and 1.1%, under a bound of 5 that the
    // smaller actual error (8.5e-4 of the mean) has now passed; the bound is 6. (The
    // estimate that summed the links' refinement bounds was 630 times the actual mean.)
    let e = &sol.elements;
    let (mut actual, mut above, mut area) = (0.0, 0.0, 0.0);
    for l in e.leaves() {
        let li = l as usize;
        if e.buried[li] {
            continue;
        }
        let a = e.visible_area(l);
        let err = (sol.state.b[li][0] - 2.0).abs();
        actual += a * err;
        area += a;
        if err > sol.error[li] {
            above += a;
        }
    }
    let actual = actual / area / mean;
    let (ratio, above) = (r.mean_error / actual, above / area);
    eprintln!(
        "estimated mean error {:.3e}, actual {actual:.3e} ({ratio:.2}x); actual above the \
         estimate on {above:.4} of the visible area",
        r.mean_error
    );
    assert!(
        (1.25..6.0).contains(&ratio),
        "estimated mean error {:.3e} is {ratio:.2} times the actual {actual:.3e}",
        r.mean_error
    );
    assert!(
        above < 0.15,
        "actual error above the estimate on {above:.3} of the area"
    );
    assert!(
        r.max_error >= r.mean_error && r.max_error < 1.0,
        "max {:.3e}",
        r.max_error
    );
}

/// Leaf luminance at 4 points of every root (parameters `(1/4 or 3/4, 1/4 or 3/4)`), as
/// `(root, value)`, `None` on a buried leaf.
fn points(sol: &Solution) -> Vec<(usize, Option<f64>)> {
    use radiosity::scene::luminance;
    let e = &sol.elements;
    let mut out = Vec::new();
    for r in 0..e.roots as u32 {
        for (u, v) in [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)] {
            let l = e.locate(r, u, v).0 as usize;
            out.push((
                r as usize,
                (!e.buried[l]).then(|| luminance(sol.state.b[l])),
            ));
        }
    }
    out
}

/// Luminance of the output mesh (the leaves' per-vertex values, as the EXR and PLY hold
/// them: [`hierarchy::leaves::leaf_mesh`], least-squares vertex values) at the points of
/// [`points`], in the same order; `None` where no output triangle holds the point.
fn output_points(patches: &PatchSet, sol: &Solution) -> Vec<Option<f64>> {
    use radiosity::output::{interpolate_with, Nodal};
    let e = &sol.elements;
    let (leaves, b, _) = hierarchy::leaves::leaf_mesh(e, patches, &sol.state.b);
    let verts = interpolate_with(&leaves, &b, 30.0, Nodal::Linear);
    let mut out = Vec::new();
    for r in 0..e.roots {
        for (u, v) in [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)] {
            let at = e.piece[r].at(u, 1.0 - u, v, 1.0 - v).0;
            let got =
                radiosity::study::bakes::probe(&verts, at, e.normal[r], 1e-4 * patches.diagonal);
            out.push(got.map(radiosity::scene::luminance));
        }
    }
    out
}

/// Clustered against unclustered on a 10^4-triangle scene (`room-spheres-8`: 10,240
/// sphere triangles and the room), at `--error 0.01 --link-rays 8 --gather-noise 0.1` (or
/// `RADIOSITY_TEN_K_ERROR`, `RADIOSITY_TEN_K_RAYS` and `RADIOSITY_TEN_K_NOISE`; the seed
/// from `RADIOSITY_TEN_K_SEED`): at least 10 times fewer initial
/// links clustered, object averages within 1%, root (input face) averages within 2% and
/// leaf points within 3% at the 99th percentile, the output meshes' values at those
/// points within 1% at the 99th percentile and, at these settings or tighter, every one
/// within 3% and every root within 1%; every root's difference within the sum of the two
/// bakes' estimated errors.
/// The unclustered bake evaluates 10^8 candidate pairs (6.4 GB peak, about 20 minutes
/// here): run by hand,
/// `cargo test --release --test tests clustered_and_unclustered_at_ten_thousand -- --ignored --nocapture`.
/// With `RADIOSITY_TEN_K_FLOOR=1` it also bakes the unclustered scene at the next seed and
/// prints how far its output points fall from the first unclustered bake's and from the
/// clustered one's: the reference's own spread, which bounds what a line on single points
/// can ask (docs/HIERARCHY.md, Clustering).
#[test]
#[ignore]
fn clustered_and_unclustered_at_ten_thousand_triangles() {
    let error = crate::env_or("RADIOSITY_TEN_K_ERROR", 0.01);
    let rays = crate::env_or("RADIOSITY_TEN_K_RAYS", 8);
    let seed = crate::env_or("RADIOSITY_TEN_K_SEED", Settings::default().seed);
    let gather_noise = crate::env_or("RADIOSITY_TEN_K_NOISE", 0.1);
    let base = Settings {
        error,
        rays,
        seed,
        gather_noise,
        ..Default::default()
    };
    let res = Resolution::DiagonalFraction(0.25);
    let t = std::time::Instant::now();
    let (p, a) = solve(
        "room-spheres-8",
        res,
        &Settings {
            clusters: Clustering::On,
            ..base.clone()
        },
    );
    let ta = t.elapsed().as_secs_f64();
    let t = std::time::Instant::now();
    let (_, b) = solve(
        "room-spheres-8",
        res,
        &Settings {
            clusters: Clustering::Off,
            ..base.clone()
        },
    );
    let tb = t.elapsed().as_secs_f64();
    let (ra, oa) = averages(&p, &a);
    let (rb, ob) = averages(&p, &b);
    let rel = |x: f64, y: f64| (x / y - 1.0).abs();
    let worst_obj = oa
        .iter()
        .zip(&ob)
        .map(|(x, y)| rel(*x, *y))
        .fold(0.0, f64::max);
    let roots: Vec<f64> = (0..ra.len())
        .filter(|&r| rb[r] > 0.0)
        .map(|r| rel(ra[r], rb[r]))
        .collect();
    let (pa, pb) = (points(&a), points(&b));
    assert_eq!(pa.len(), pb.len());
    // A point on a leaf buried in either bake (the two split the leaves around the light
    // differently) is left out.
    let pts: Vec<f64> = pa
        .iter()
        .zip(&pb)
        .filter_map(|(x, y)| match (x.1, y.1) {
            (Some(x), Some(y)) if y > 0.0 => Some(rel(x, y)),
            _ => None,
        })
        .collect();
    // The same points on the output meshes, where each bake's leaves of different sizes
    // are joined by their vertex values as a user sees them.
    let (qa, qb) = (output_points(&p, &a), output_points(&p, &b));
    let out_pts = output_differences((&qa, &pa), (&qb, &pb));
    let summary = |v: &[f64]| {
        let mut s = v.to_vec();
        s.sort_by(f64::total_cmp);
        let q = |p: f64| s[((s.len() - 1) as f64 * p) as usize];
        (
            q(0.5),
            q(0.99),
            s[s.len() - 1],
            s.iter().filter(|&&d| d > 0.03).count(),
        )
    };
    let (r50, r99, rmax, rover) = summary(&roots);
    let (p50, p99, pmax, pover) = summary(&pts);
    let (o50, o99, omax, oover) = summary(&out_pts);
    let (ia, ib) = (a.report.initial_links, b.report.initial_links);
    eprintln!(
        "clustered {ta:.0} s, unclustered {tb:.0} s; initial links {ia} vs {ib} (1/{:.0}); \
         links {} vs {}; objects worst {worst_obj:.4}; roots median {r50:.4}, 99% {r99:.4}, \
         worst {rmax:.4}, {rover} of {} over 3%; points median {p50:.4}, 99% {p99:.4}, worst \
         {pmax:.4}, {pover} of {} over 3%; output points median {o50:.4}, 99% {o99:.4}, \
         worst {omax:.4}, {oover} of {} over 3%; rows over one {} vs {}",
        ib as f64 / ia as f64,
        a.report.links,
        b.report.links,
        roots.len(),
        pts.len(),
        out_pts.len(),
        a.report.rows_over_one,
        b.report.rows_over_one
    );
    for (k, (x, y)) in oa.iter().zip(&ob).enumerate() {
        eprintln!(
            "  {}: {x:.5} vs {y:.5} ({:+.3}%)",
            p.objects[k],
            100.0 * (x / y - 1.0)
        );
    }
    let mut order: Vec<usize> = (0..ra.len()).filter(|&r| rb[r] > 0.0).collect();
    order.sort_by(|&x, &y| rel(ra[y], rb[y]).total_cmp(&rel(ra[x], rb[x])));
    let leaves_under = |sol: &Solution, r: usize| {
        sol.elements
            .leaves()
            .filter(|&l| sol.elements.root[l as usize] as usize == r)
            .count()
    };
    // A root's estimated error: the area mean of its leaves' (absolute radiosity).
    let root_error = |sol: &Solution, r: usize| {
        let e = &sol.elements;
        let (mut s, mut a) = (0.0, 0.0);
        for l in e.leaves() {
            let li = l as usize;
            if e.root[li] as usize == r && !e.buried[li] {
                s += e.area[li] * sol.error[li];
                a += e.area[li];
            }
        }
        if a > 0.0 {
            s / a
        } else {
            0.0
        }
    };
    let beyond = order
        .iter()
        .filter(|&&r| (ra[r] - rb[r]).abs() > root_error(&a, r) + root_error(&b, r))
        .count();
    eprintln!(
        "roots whose averages differ by more than the sum of their estimated errors: {beyond}"
    );
    for &r in order.iter().take(25) {
        let c = p.centroid[r];
        eprintln!(
            "  root {r} ({}, at {:.2} {:.2} {:.2}, area {:.2e}): {:.5} vs {:.5} ({:+.2}%), \
             estimated errors {:.5} and {:.5}, leaves {} vs {}",
            p.objects[p.object[r] as usize],
            c.x,
            c.y,
            c.z,
            p.area[r],
            ra[r],
            rb[r],
            100.0 * (ra[r] / rb[r] - 1.0),
            root_error(&a, r),
            root_error(&b, r),
            leaves_under(&a, r),
            leaves_under(&b, r)
        );
    }
    // Measured (docs/HIERARCHY.md, Clustering) at this test's settings, --error 0.01,
    // --link-rays 8 and --gather-noise 0.1 (2026-12-06): 1/34 of the initial links,
    // objects within 0.18%, roots within 0.23% at the 99th percentile and every one within
    // 0.46%, leaf points 0.26%, output points 0.19% and every one within 3% (worst
    // 2.42%); clustered 125 s, unclustered 669 s; at seed 2 every root within 0.71%,
    // output points worst 2.50%. Without the noise target: roots within
    // 0.36% at the 99th percentile (worst 1.95%, one sphere face), leaf points 0.41%,
    // output points 0.24% (worst 2.38%); 96 s and 997 s (a busy hour). With the default
    // 4 x 4 rays a link and the default split receivers and split shadows: at --error
    // 0.05, 1/55 of the initial links, objects within 0.17%, roots within 1.81% at the 99th percentile (0.80% before receivers and
    // shadows were split: single sphere faces, one leaf each, whose estimated errors are
    // 3-8% in both bakes), points within 2.00% at the 99th percentile, every root's
    // difference within the sum of the two bakes' estimated errors. At --error 0.02 (a
    // first version of the shadow rule): 1/38, 0.24%, 1.26%, 1.74%, none beyond. A leaf's
    // value at a point is its mean over the leaf, and the two bakes split the room's faces
    // differently (a leaf of one may be four of the other's): the worst leaf points
    // differ by 28% at 0.05, 15% at 0.02. The output meshes, which join the leaves by
    // their vertex values as the files hold them, agree within 0.75% at the 99th
    // percentile at 0.05 (9 of 41,130 points over 3%, worst 7.2%, on room faces of leaves
    // 20 to 40 cm across) and 0.67% at 0.02 (2 over 3%, worst 4.6%, one sphere face).
    assert!(ia * 10 <= ib, "initial links {ia} vs {ib}");
    assert!(worst_obj < 0.01, "object averages differ by {worst_obj}");
    assert!(
        r99 < 0.02,
        "root averages differ by {r99} at the 99th percentile"
    );
    assert!(p99 < 0.03, "points differ by {p99} at the 99th percentile");
    assert!(
        o99 < 0.01,
        "output points differ by {o99} at the 99th percentile"
    );
    assert_eq!(
        beyond, 0,
        "roots whose difference is beyond their estimated errors"
    );
    // Every output point within 3%, at the settings this is measured at (with the
    // default 4 × 4 rays a link, 2 to 9 of them were over: docs/HIERARCHY.md), and with
    // the gather's visibility noise held to a tenth of the tolerance every root within
    // 1% (without it, the worst 1.95% to 2.41%: single sphere faces whose light is partly
    // hidden, the final gather's visibility noise in both bakes).
    if error <= 0.01 && rays >= 8 {
        assert_eq!(oover, 0, "output points over 3% (worst {omax})");
        if gather_noise <= 0.1 {
            assert!(rmax <= 0.01, "roots differ by up to {rmax}");
        }
    }
    eprintln!(
        "(not asserted) roots worst {rmax:.4}, points worst {pmax:.4}, output points worst \
         {omax:.4}"
    );
    // The reference's own spread: the unclustered bake again with another seed, against
    // the first and against the clustered one (docs/HIERARCHY.md, Clustering).
    if std::env::var("RADIOSITY_TEN_K_FLOOR").is_ok_and(|v| v == "1") {
        let (_, c) = solve(
            "room-spheres-8",
            res,
            &Settings {
                clusters: Clustering::Off,
                seed: base.seed + 1,
                ..base.clone()
            },
        );
        let pc = points(&c);
        let qc = output_points(&p, &c);
        for (name, d) in [
            (
                "unclustered seed 1 vs seed 2",
                output_differences((&qb, &pb), (&qc, &pc)),
            ),
            (
                "clustered seed 1 vs unclustered seed 2",
                output_differences((&qa, &pa), (&qc, &pc)),
            ),
        ] {
            let (m, q99, worst, over) = summary(&d);
            eprintln!(
                "{name}: output points median {m:.4}, 99% {q99:.4}, worst {worst:.4}, {over} of \
                 {} over 3%",
                d.len()
            );
        }
    }
}

/// One bake's output points ([`output_points`]) and leaf points ([`points`]).
type Bake<'a> = (&'a [Option<f64>], &'a [(usize, Option<f64>)]);

/// Relative differences of two bakes' output points ([`output_points`]) where both have a
/// value and neither point's leaf is buried ([`points`]).
fn output_differences((qa, pa): Bake<'_>, (qb, pb): Bake<'_>) -> Vec<f64> {
    qa.iter()
        .zip(qb)
        .zip(pa.iter().zip(pb))
        .filter_map(|((x, y), (la, lb))| match (x, y, la.1, lb.1) {
            (Some(x), Some(y), Some(_), Some(_)) if *y > 0.0 => Some((x / y - 1.0).abs()),
            _ => None,
        })
        .collect()
}

/// Radiosity (luminance) of the output vertex at `p` with normal `+y` in `v`.
fn floor_vertex(v: &radiosity::output::VertexRadiosity, p: glam::DVec3) -> Option<f64> {
    (0..v.positions.len())
        .find(|&k| v.positions[k].as_dvec3().distance(p) < 1e-4 && v.normals[k].y > 0.99)
        .map(|k| {
            let c = v.rgb[k];
            radiosity::scene::luminance([f64::from(c[0]), f64::from(c[1]), f64::from(c[2])])
        })
}

/// `room-spheres-8`'s floor in the spheres' shadows against Mitsuba 3
/// (`docs/reference/room-spheres-8-shadow-mitsuba.csv`, standard errors at most 0.2%): a
/// 1 m² light over floor roots of 0.14 m², so the refinement splits the light, and its
/// pieces' partly visible links fall within the tolerance one by one while the floor
/// roots keep the shadow boundaries across them. With `split_shadows` a receiver whose
/// links' shadows add up to more than twice its tolerance is split. Measured
/// (docs/HIERARCHY.md, Shadows across receivers), at the default settings: mean error 1.0%,
/// largest 1.7% (without: 2.4% and 5.5%; 17.4% and 28.4% without `split_receivers` either,
/// at `--error 0.05`).
#[test]
fn shadows_across_receivers_split_them() {
    let reference = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/docs/reference/room-spheres-8-shadow-mitsuba.csv"
    ))
    .expect("reference");
    let s = Settings {
        clusters: Clustering::On,
        split_shadows: true,
        split_receivers: true,
        ..Settings::default()
    };
    let (patches, sol) = solve("room-spheres-8", Resolution::DiagonalFraction(0.25), &s);
    // The output vertices as `mesh.ply` has them: the bake's leaf mesh and vertex rule.
    let (leaves, b, _) = hierarchy::leaves::leaf_mesh(&sol.elements, &patches, &sol.state.b);
    let v =
        radiosity::output::interpolate_with(&leaves, &b, 30.0, radiosity::output::Nodal::Linear);
    let (mut sum, mut n, mut worst) = (0.0, 0, 0.0f64);
    for line in reference.lines().skip(1) {
        let x: Vec<f64> = line
            .split(',')
            .map(|w| w.parse().expect("number"))
            .collect();
        let Some(b) = floor_vertex(&v, glam::DVec3::new(x[0], x[1], x[2])) else {
            continue;
        };
        let e = (b / x[6] - 1.0).abs();
        eprintln!(
            "({}, {}, {}): {b:.5} against {:.5} ({:+.2}%)",
            x[0],
            x[1],
            x[2],
            x[6],
            100.0 * (b / x[6] - 1.0)
        );
        sum += e;
        n += 1;
        worst = worst.max(e);
    }
    assert!(n >= 10, "{n} reference points found on the floor");
    assert!(worst < 0.03, "worst point {worst}");
    assert!(sum / (n as f64) < 0.015, "mean error {}", sum / n as f64);
}

/// A wall leaf a little above a ground much larger than its distance gathers that ground
/// cut into pieces, not whole: whole, its traced visible fraction (`4 × 4` segments whose
/// kernel is thousands of times its mean where they land by the leaf) came out far above
/// 1, and 51 leaves of `city-2` at `--error 0.05` summed their factors over 1 beyond 3
/// bars, the largest to 6.6 (docs/HIERARCHY.md, *What does not hold yet*).
#[test]
fn a_huge_near_source_is_gathered_in_pieces() {
    let s = Settings {
        error: 0.05,
        ..Settings::default()
    };
    let (_, sol) = solve("city-2", Resolution::DiagonalFraction(0.25), &s);
    let (sum, bar) = sol.report.max_row_sum;
    assert!(
        sum <= 1.0 + bar.allowance(5.0),
        "largest leaf factor sum {sum} ± {bar}"
    );
    let over = sol.report.rows_over_one;
    assert!(
        over * 500 <= sol.report.leaves,
        "{over} of {} leaves over 1 beyond 3 bars",
        sol.report.leaves
    );
}

/// The closed cube of `cube_furnace_with_clusters` with every factor integrated to 1e-10
/// (element links by `quadrature` and `accuracy`, solver tolerance 1e-10) and cluster
/// transfers by `cluster_quadrature`. Returns the report, the worst leaf's `|B - 2|`, the
/// power unaccounted for and the seconds taken.
fn integrated_cube_furnace(cluster_quadrature: f64) -> (hierarchy::Report, f64, f64, f64) {
    let s = Settings {
        error: 0.02,
        min_area: Some(1.0 / 1024.0),
        quadrature: 1e-10,
        accuracy: 0.0,
        tolerance: 1e-10,
        clusters: Clustering::On,
        cluster_quadrature,
        ..Settings::default()
    };
    let t = std::time::Instant::now();
    let (_, sol) = solve("cube", Resolution::Patches(1536), &s);
    let seconds = t.elapsed().as_secs_f64();
    let r = sol.report;
    let mut worst = 0.0f64;
    for l in sol.elements.leaves() {
        for c in sol.state.b[l as usize] {
            worst = worst.max((c - 2.0).abs());
        }
    }
    let balance = (0..3)
        .map(|c| (r.emitted[c] - r.absorbed[c]).abs() / r.emitted[c])
        .fold(0.0, f64::max);
    eprintln!(
        "cluster quadrature {cluster_quadrature:e}: {} cluster links, {} initial links, {} \
         leaves, worst |B - 2| {worst:.2e}, power {balance:.2e}, largest factor sum {:?}, \
         {} point factors, {seconds:.1} s",
        r.cluster_links, r.initial_links, r.leaves, r.max_row_sum, r.evals
    );
    (r, worst, balance, seconds)
}

/// The hierarchical method's furnace check (`closed_cube_links_sum_to_one_and_the_furnace_holds`)
/// with cluster links in use, their transfers integrated to 1e-10: every leaf's factors
/// sum to 1 within 1e-8, B = 2 within 1e-6 on every leaf, emitted equals absorbed within
/// 1e-6. Measured: 66,934 cluster links, worst leaf 1.1e-10, power 1.1e-10, factor sums
/// within 2e-12 of 1 (with the transfers sampled, as by default: 0.14% and 4.6e-5).
#[test]
fn furnace_holds_with_cluster_links_integrated() {
    let (r, worst, balance, _) = integrated_cube_furnace(1e-10);
    assert!(
        r.cluster_links > 60_000,
        "{} cluster links",
        r.cluster_links
    );
    assert!(
        (r.max_row_sum.0 - 1.0).abs() < 1e-8,
        "largest factor sum {:?}",
        r.max_row_sum
    );
    assert!(worst < 1e-6, "worst leaf |B - 2| = {worst:e}");
    assert!(balance < 1e-6, "power balance {balance:e}");
}

/// docs/HIERARCHY.md's table of the integrated furnace by cluster quadrature tolerance
/// (`cargo test --release --test tests integrated_furnace_by_tolerance -- --ignored
/// --nocapture`).
#[test]
#[ignore]
fn integrated_furnace_by_tolerance() {
    for q in [f64::INFINITY, 1e-2, 1e-4, 1e-6, 1e-8, 1e-10] {
        integrated_cube_furnace(q);
    }
}

/// A leaf that traces its own view of a cluster link's source keeps the link's fraction's
/// standard error in its bar, as the piece's unoccluded factor times it. Taken as the
/// traced factor times the fraction's relative error instead, it grew without bound where
/// the link was almost hidden (fractions near 1e-7) and the leaf saw the source: on this
/// bake a sphere leaf of radiosity 0.043 had an estimated error of 7.9, 41 times the mean
/// radiosity, and the mean estimated error was 2.4% against 2.0%.
#[test]
fn estimated_errors_stay_bounded_where_cluster_links_are_almost_hidden() {
    let s = Settings {
        error: 0.05,
        clusters: Clustering::On,
        split_receivers: true,
        descend: 0.1,
        ..Default::default()
    };
    let (_, sol) = solve("room-spheres-24", Resolution::DiagonalFraction(0.25), &s);
    let r = &sol.report;
    eprintln!(
        "estimated error per leaf: max {:.3e}, mean {:.3e} of the mean radiosity",
        r.max_error, r.mean_error
    );
    assert!(
        r.max_error < 1.0 && r.mean_error < 0.03,
        "max {:.3e}, mean {:.3e}",
        r.max_error,
        r.mean_error
    );
}
