//! Form-factor stages against raw Embree loops over the same rays.
//!
//! `cargo bench --bench formfactor` times, on the Cornell box at about 400 patches:
//! - `form factors/area-stratified`: the whole stage (sampling, kernel, rays, assembly);
//! - `form factors/raw rtcOccluded1`: only `rtcOccluded1` over the exact ray set that stage
//!   casts (recorded once), with the same rayon thread pool;
//! - `form factors/hemisphere` and `form factors/raw rtcIntersect1`: the same for
//!   hemisphere shooting, whose raw loop is the closest-hit query;
//! - `form factors/<estimator> raw packets of 16`: the same rays through `rtcOccluded16`
//!   or `rtcIntersect16`, 16 consecutive rays per packet;
//!
//! and prints the ratio of their ray rates, measured interleaved in one run.

#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};

use radiosity::bench::{format_ratios, ratio, raw_loop, raw_loop16, record};
use radiosity::formfactor::{compute, Context};
use radiosity::mesh::{PatchSet, Resolution};
use radiosity::pipeline::EstimatorChoice;
use radiosity::scene::Scene;
use radiosity::visibility::Visibility;

fn bench(c: &mut Criterion) {
    let scene = Scene::load("cornell").expect("built-in scene");
    let patches = PatchSet::build(&scene, Resolution::Patches(400)).expect("patches");
    let vis = Visibility::new(&patches).expect("embree");
    let ctx = Context {
        patches: &patches,
        vis: &vis,
        seed: 1,
    };
    let cases = [
        (
            "area-stratified",
            "raw rtcOccluded1",
            EstimatorChoice::AreaStratified {
                strata: 4,
                replicates: 4,
            },
        ),
        (
            "hemisphere",
            "raw rtcIntersect1",
            EstimatorChoice::Hemisphere {
                strata: 16,
                replicates: 4,
            },
        ),
    ];

    // Interleaved ratio measurement in one run (medians of 5).
    let lines: Vec<_> = cases.iter().map(|(_, _, c)| ratio(&ctx, c, 5)).collect();
    print!("{}", format_ratios(&lines, rayon::current_num_threads()));

    let mut g = c.benchmark_group("form factors");
    g.sample_size(10);
    for (name, raw_name, choice) in &cases {
        let est = choice.build();
        let rays = record(&ctx, choice);
        g.throughput(Throughput::Elements(rays.len() as u64));
        g.bench_function(*name, |b| b.iter(|| compute(&ctx, est.as_ref(), &|_| {})));
        g.bench_function(*raw_name, |b| b.iter(|| raw_loop(&vis, &rays)));
        g.bench_function(format!("{name} raw packets of 16"), |b| {
            b.iter(|| raw_loop16(&vis, &rays))
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
