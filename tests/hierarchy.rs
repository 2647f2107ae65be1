//! Hierarchical radiosity against closed forms: closure and the furnace, the notes' shelf,
//! crack-free output, determinism, and refinement where visibility changes.

use radiosity::hierarchy::{self, Settings, Solution};
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

/// `Σ F` over the links into each leaf and its ancestors: 1 in a closed scene.
fn leaf_factor_sums(sol: &Solution) -> Vec<(u32, f64)> {
    let e = &sol.elements;
    let mut down = vec![0.0f64; e.len()];
    for p in 0..e.len() {
        let own: f64 = sol.links[p].iter().map(|l| l.f).sum();
        let parent = e.parent[p];
        down[p] = own
            + if parent == u32::MAX {
                0.0
            } else {
                down[parent as usize]
            };
    }
    e.leaves().map(|l| (l, down[l as usize])).collect()
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
    let sums = leaf_factor_sums(&sol);
    let worst = sums
        .iter()
        .map(|&(l, f)| ((f - 1.0).abs(), l, f))
        .fold((0.0, 0, 0.0), |a, b| if b.0 > a.0 { b } else { a });
    assert!(worst.0 < 1e-8, "leaf {} sums to {}", worst.1, worst.2);
    for l in sol.elements.leaves() {
        for c in sol.state.b[l as usize] {
            assert!((c - 2.0).abs() < 1e-6, "leaf {l}: B = {c}");
        }
    }
    let r = &sol.report;
    for c in 0..3 {
        let rel = (r.emitted[c] - r.absorbed[c]).abs() / r.emitted[c];
        assert!(rel < 1e-6, "power balance {rel:e}");
    }
}
