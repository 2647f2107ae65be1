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
