//! Form-factor stage against a raw Embree occlusion loop over the same rays.
//!
//! `cargo bench --bench formfactor` times, on the Cornell box at about 400 patches:
//! - `form factors/area-stratified`: the whole stage (sampling, kernel, rays, assembly);
//! - `form factors/raw rtcOccluded1`: only `rtcOccluded1` over the exact ray set the
//!   stage casts (recorded once), with the same rayon thread pool;
//!
//! and prints the ratio of their ray rates, measured interleaved in one run.

use std::time::Instant;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use glam::Vec3;
use rayon::prelude::*;

use radiosity::formfactor::{compute, AreaMc, Context, Row};
use radiosity::mesh::{PatchSet, Resolution};
use radiosity::scene::Scene;
use radiosity::visibility::Visibility;

type Ray = (Vec3, Vec3, f32);

fn record(est: &AreaMc, ctx: &Context) -> Vec<Ray> {
    (0..ctx.patches.len())
        .into_par_iter()
        .flat_map_iter(|a| {
            let mut rays = Vec::new();
            let mut row = Row::default();
            est.row_with(ctx, a, &mut row, &mut |x, n_x, y, n_y| {
                rays.push(ctx.vis.segment_ray(x, n_x, y, n_y));
                true
            });
            rays
        })
        .collect()
}

fn raw_loop(vis: &Visibility, rays: &[Ray]) -> usize {
    rays.par_chunks(4096)
        .map(|ch| {
            ch.iter()
                .filter(|r| vis.raw().occluded1(r.0, r.1, 0.0, r.2))
                .count()
        })
        .sum()
}

fn bench(c: &mut Criterion) {
    let scene = Scene::load("cornell").expect("built-in scene");
    let patches = PatchSet::build(&scene, Resolution::Patches(400)).expect("patches");
    let vis = Visibility::new(&patches).expect("embree");
    let ctx = Context {
        patches: &patches,
        vis: &vis,
        seed: 1,
    };
    let est = AreaMc::default();
    let rays = record(&est, &ctx);

    // Interleaved ratio measurement in one run (medians of 5).
    let mut stage = Vec::new();
    let mut raw = Vec::new();
    for _ in 0..5 {
        let t = Instant::now();
        let ff = compute(&ctx, &est, &|_| {});
        stage.push(ff.rays as f64 / t.elapsed().as_secs_f64());
        let t = Instant::now();
        std::hint::black_box(raw_loop(&vis, &rays));
        raw.push(rays.len() as f64 / t.elapsed().as_secs_f64());
    }
    stage.sort_by(f64::total_cmp);
    raw.sort_by(f64::total_cmp);
    let (s, r) = (stage[2], raw[2]);
    println!(
        "cornell {} patches, {} rays, {} threads: form-factor stage {:.2} Mrays/s, raw rtcOccluded1 {:.2} Mrays/s, ratio {:.3}",
        patches.len(),
        rays.len(),
        rayon::current_num_threads(),
        s / 1e6,
        r / 1e6,
        s / r
    );

    let mut g = c.benchmark_group("form factors");
    g.sample_size(10);
    g.throughput(Throughput::Elements(rays.len() as u64));
    g.bench_function("area-stratified", |b| {
        b.iter(|| compute(&ctx, &est, &|_| {}))
    });
    g.bench_function("raw rtcOccluded1", |b| b.iter(|| raw_loop(&vis, &rays)));
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
