//! The notes' "infinite shelf" (radiosidade.md, "Prateleira Infinita"): a long finite
//! shelf, one patch across each strip and sliced along its length, reproduces the table
//! of the notes at its middle slice.

use radiosity::mesh::{PatchSet, Resolution};
use radiosity::pipeline::{self, BakeConfig, Quiet};
use radiosity::scene::Scene;
use radiosity::solve::{Method, Options};

/// (rho_A, rho_B, rho_C), (E_A, E_B, E_C), (B_A, B_B, B_C) as printed in the notes
/// (row 4's B_B restored to 1.02906, see NOTES.md).
pub(crate) const TABLE: [([f64; 3], [f64; 3], [f64; 3]); 4] = [
    (
        [0.0, 0.5, 1.0 / 3.0],
        [1.0, 0.0, 0.0],
        [1.0, 0.11660, 0.10354],
    ),
    (
        [0.1, 0.5, 1.0 / 3.0],
        [1.0, 0.0, 0.0],
        [1.00709, 0.11743, 0.10428],
    ),
    ([0.5, 0.0, 0.5], [0.0, 1.0, 0.0], [0.21133, 1.0, 0.21133]),
    (
        [0.1, 0.1, 0.5],
        [1.0, 1.0, 0.0],
        [1.04647, 1.02906, 0.32853],
    ),
];

#[test]
fn middle_slice_reproduces_the_notes_table() {
    let mut scene = Scene::load("shelf").expect("built-in shelf");
    let (lo, hi) = scene.bounds();
    let mid_x = 0.5 * (lo.x + hi.x);
    // Widths are 1 and sqrt(3) < 2, so an edge limit of 2 gives one patch across each strip.
    let patches = PatchSet::build(&scene, Resolution::MaxEdge(2.0)).expect("patches");
    let slices = patches.len() / 3;
    assert_eq!(patches.len(), 3 * slices);
    assert_eq!(slices % 2, 1, "an odd number of slices has a middle one");
    let (ff, _, _) = pipeline::form_factors(&patches, &BakeConfig::default().estimator, 1, &Quiet)
        .expect("form factors");
    let middle = |name: &str| -> usize {
        let m = scene.material_index(name).expect("material") as u32;
        (0..patches.len())
            .filter(|&i| patches.material[i] == m)
            .min_by(|&a, &b| {
                let da = (patches.centroid[a].x - mid_x).abs();
                let db = (patches.centroid[b].x - mid_x).abs();
                da.total_cmp(&db)
            })
            .expect("a patch of that strip")
    };
    let ids = [middle("A"), middle("B"), middle("C")];
    for (row, (rho, emit, expected)) in TABLE.iter().enumerate() {
        for (k, name) in ["A", "B", "C"].iter().enumerate() {
            scene
                .set_material(name, [rho[k]; 3], [emit[k]; 3])
                .expect("valid material");
        }
        let patches = PatchSet {
            materials: scene.materials.clone(),
            ..patches.clone()
        };
        let (b, report) =
            pipeline::solve_radiosity(&patches, &ff, Method::GaussSeidel, &Options::default())
                .expect("solve");
        assert!(report.converged);
        for k in 0..3 {
            let got = b[ids[k]][0];
            eprintln!(
                "row {} B_{}: {got:.5} (notes {:.5})",
                row + 1,
                ["A", "B", "C"][k],
                expected[k]
            );
            assert!(
                (got - expected[k]).abs() <= 2e-3,
                "row {}: B_{} = {got:.5}, the notes give {:.5}",
                row + 1,
                ["A", "B", "C"][k],
                expected[k]
            );
        }
    }
}
