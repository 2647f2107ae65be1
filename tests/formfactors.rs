use radiosity::formfactor::{compute, AreaMc, Context, Pattern};
use radiosity::mesh::{PatchSet, Resolution};
use radiosity::scene::Scene;
use radiosity::visibility::Visibility;

#[test]
fn smoke_parallel_plates() {
    let scene = Scene::load("plates-parallel").unwrap();
    let patches = PatchSet::build(&scene, Resolution::MaxEdge(10.0)).unwrap();
    let vis = Visibility::new(&patches).unwrap();
    let ctx = Context { patches: &patches, vis: &vis, seed: 1 };
    for strata in [4, 16, 64] {
        let est = AreaMc { pattern: Pattern::Stratified, strata, replicates: 16 };
        let ff = compute(&ctx, &est, &|_| {});
        eprintln!("strata {strata}: F01 = {} +- {} rays {}", ff.get(0, 1), ff.stderr(0, 1), ff.rays);
    }
    let scene = Scene::load("plates-perpendicular").unwrap();
    let patches = PatchSet::build(&scene, Resolution::MaxEdge(10.0)).unwrap();
    let vis = Visibility::new(&patches).unwrap();
    let ctx = Context { patches: &patches, vis: &vis, seed: 1 };
    for strata in [4, 16, 64] {
        let est = AreaMc { pattern: Pattern::Stratified, strata, replicates: 16 };
        let ff = compute(&ctx, &est, &|_| {});
        eprintln!("perp strata {strata}: F01 = {} +- {} (exact 0.2000438)", ff.get(0, 1), ff.stderr(0, 1));
    }
}

#[test]
fn smoke_cube_rows() {
    let scene = Scene::load("cube").unwrap();
    for res in [1.0, 0.5, 0.25, 0.125] {
        let patches = PatchSet::build(&scene, Resolution::MaxEdge(res)).unwrap();
        let vis = Visibility::new(&patches).unwrap();
        let ctx = Context { patches: &patches, vis: &vis, seed: 1 };
        let est = AreaMc::default();
        let t = std::time::Instant::now();
        let ff = compute(&ctx, &est, &|_| {});
        let d = ff.diagnostics();
        let worst = (0..ff.len()).map(|i| (ff.row_sum(i) - 1.0).abs()).fold(0.0, f64::max);
        let worst_se = (0..ff.len()).map(|i| ff.row_sum_stderr(i)).fold(0.0, f64::max);
        eprintln!("cube h={res}: n={} worst |rowsum-1| {worst:.2e} max se {worst_se:.2e} recip {:.1e} rays {} {:?}", ff.len(), d.reciprocity, ff.rays, t.elapsed());
    }
}
