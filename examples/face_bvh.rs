//! The raw `rtcIntersect16` loop over a hemisphere stage's recorded rays, traced against
//! two Embree scenes of the same surfaces: the patch triangles (what the flat path traced
//! before, and still traces for a patch set without face grids) and the scene's faces
//! traced whole (what [`Visibility::new`] builds now: patches are regular grids of the
//! input faces, so a hit on a face names its patch from the face's coordinates). This
//! measures what the smaller scene saves Embree where the patch BVH no longer stays in the
//! caches (docs/PERFORMANCE.md, section 1, *Embree's share of the bake*).
//!
//! `cargo run --release --example face_bvh -- PATCHES`: the Cornell box at about PATCHES
//! patches (default 300,000), 4 x 4 directions x 4 replicates per patch, one thread,
//! three rounds of both loops in turn.

use std::time::Instant;

use radiosity::bench::{pool, raw_loop16, record};
use radiosity::formfactor::Context;
use radiosity::mesh::{PatchSet, Resolution};
use radiosity::pipeline::EstimatorChoice;
use radiosity::scene::Scene;
use radiosity::visibility::Visibility;

fn main() {
    let n: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(300_000);
    let scene = Scene::load("cornell").expect("built-in scene");
    let p = PatchSet::build(&scene, Resolution::Patches(n)).expect("mesh");
    // The same patches without their face grids: traced by their triangles.
    let vis = Visibility::new(&PatchSet {
        grids: Vec::new(),
        ..p.clone()
    })
    .expect("Embree scene");
    let vis_faces = Visibility::new(&p).expect("Embree scene");
    eprintln!(
        "{} patches ({} triangles traced); {} faces traced whole ({} triangles)",
        p.len(),
        vis.traced_triangles(),
        vis_faces.whole_faces(),
        vis_faces.traced_triangles()
    );
    let ctx = Context {
        patches: &p,
        vis: &vis_faces,
        seed: 1,
    };
    let choice = EstimatorChoice::Hemisphere {
        strata: 4,
        replicates: 4,
    };
    let pool = pool(1, true).expect("thread pool");
    pool.install(|| {
        let rec = record(&ctx, &choice);
        for round in 0..3 {
            let t = Instant::now();
            std::hint::black_box(raw_loop16(&vis, &rec));
            let tp = t.elapsed().as_secs_f64();
            let t = Instant::now();
            std::hint::black_box(raw_loop16(&vis_faces, &rec));
            let tf = t.elapsed().as_secs_f64();
            eprintln!(
                "round {round}: patch triangles {tp:.3} s, input faces {tf:.3} s, ratio {:.3}",
                tf / tp
            );
        }
    });
}
