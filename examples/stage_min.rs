//! The form-factor stage against the raw `rtcOccluded16` / `rtcIntersect16` loop over the
//! same rays, by the *smallest* time of each over many alternated samples: on a host shared
//! with other work, the minimum is what the code costs when nothing else runs, where the
//! median of `radiosity bench` moves with the load (docs/PERFORMANCE.md, section 1).
//!
//! `cargo run --release --example stage_min -- ESTIMATOR PATCHES THREADS REPEATS
//! [triangles]`, with ESTIMATOR `area` (stratified, 4 x 4 x 4 pairs, as the bench) or
//! `hemisphere` (16 x 16 x 4 rays), on the Cornell box. With `triangles`, the stage and the
//! loop are also timed on the scene of the patches' own triangles (what the flat path
//! traced before its faces were traced whole), and the stage on the faces is set against
//! that loop too.

use std::time::Instant;

use radiosity::bench::{pool, raw_loop16, record};
use radiosity::formfactor::{self, Context};
use radiosity::mesh::{PatchSet, Resolution};
use radiosity::pipeline::EstimatorChoice;
use radiosity::scene::Scene;
use radiosity::visibility::Visibility;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let arg =
        |k: usize, default: usize| args.get(k).and_then(|s| s.parse().ok()).unwrap_or(default);
    let (patches, threads, repeats) = (arg(1, 400), arg(2, 1), arg(3, 25));
    let triangles = args.get(4).is_some_and(|s| s == "triangles");
    let choice = match args.first().map(String::as_str) {
        Some("hemisphere") => EstimatorChoice::Hemisphere {
            strata: 16,
            replicates: 4,
        },
        _ => EstimatorChoice::AreaStratified {
            strata: 4,
            replicates: 4,
        },
    };
    let scene = Scene::load("cornell").expect("built-in scene");
    let p = PatchSet::build(&scene, Resolution::Patches(patches)).expect("mesh");
    let vis = Visibility::new(&p).expect("Embree scene");
    // The same patches without their face grids: traced by their triangles.
    let vis_t = Visibility::new(&PatchSet {
        grids: Vec::new(),
        ..p.clone()
    })
    .expect("Embree scene");
    let ctx = Context {
        patches: &p,
        vis: &vis,
        seed: 1,
    };
    let ctx_t = Context { vis: &vis_t, ..ctx };
    let pool = pool(threads, true).expect("thread pool");
    pool.install(|| {
        let est = choice.build();
        let rec = record(&ctx, &choice);
        let t = Instant::now();
        let rays = formfactor::compute(&ctx, est.as_ref(), &|_| {}).rays;
        // Samples of about 50 ms: short enough to find quiet moments.
        let k = ((0.05 / t.elapsed().as_secs_f64()).ceil() as usize).max(1);
        // The smallest time of: the stage, the loop, and (with `triangles`) both on the
        // patch triangles.
        let mut best = [f64::INFINITY; 4];
        let mut time = |slot: usize, f: &dyn Fn()| {
            let t = Instant::now();
            for _ in 0..k {
                f();
            }
            best[slot] = best[slot].min(t.elapsed().as_secs_f64() / k as f64);
        };
        for _ in 0..repeats {
            time(0, &|| {
                drop(formfactor::compute(&ctx, est.as_ref(), &|_| {}))
            });
            time(1, &|| {
                std::hint::black_box(raw_loop16(ctx.vis, &rec));
            });
            if triangles {
                time(2, &|| {
                    drop(formfactor::compute(&ctx_t, est.as_ref(), &|_| {}))
                });
                time(3, &|| {
                    std::hint::black_box(raw_loop16(ctx_t.vis, &rec));
                });
            }
        }
        let [stage, raw, stage_t, raw_t] = best;
        println!(
            "{} patches={} rays={rays} threads={threads} stage_min={:.3} ms \
             raw16_min={:.3} ms raw16_min/stage_min={:.4}",
            est.name(),
            p.len(),
            stage * 1e3,
            raw * 1e3,
            raw / stage
        );
        if triangles {
            println!(
                "patch triangles: stage_min={:.3} ms raw16_min={:.3} ms \
                 raw16_min/stage_min={:.4}; their raw16_min over the faces' stage_min={:.4}",
                stage_t * 1e3,
                raw_t * 1e3,
                raw_t / stage_t,
                raw_t / stage
            );
        }
    });
}
