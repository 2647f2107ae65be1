//! Two-sided faces: the closed cube wound outward (Blender's default cube), made
//! two-sided, must give on its inner sides the closed forms of the cube wound inward; the
//! outward room is warned about before any form factor; the hierarchical method refuses
//! two-sided faces before any work.

use std::sync::Mutex;

use radiosity::matrix::FormFactors;
use radiosity::mesh::{PatchSet, Resolution};
use radiosity::pipeline::{self, BakeConfig, EstimatorChoice, Observer, Quiet};
use radiosity::scene::Scene;

/// Howell C-14, unit squares with a common edge.
const F_PERPENDICULAR: f64 = 0.200_043_776_075_403_16;
/// Howell C-11, opposed unit squares at distance 1.
const F_PARALLEL: f64 = 0.199_824_895_698_387_5;

fn temp_dir(tag: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("radiosity-2s-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

/// The unit cube of `scenes/cube.obj` with every face wound outward (normals out of the
/// room), written next to its MTL (a furnace: rho 0.5, E 1); `extra` goes into the MTL.
fn outward_cube(dir: &std::path::Path, extra: &str) -> String {
    let obj = "mtllib cube.mtl\nusemtl wall\n\
        v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\nv 1 1 1\nv 0 1 1\n\
        o z0\nf 4 3 2 1\no z1\nf 6 7 8 5\no y0\nf 2 6 5 1\no y1\nf 8 7 3 4\n\
        o x0\nf 5 8 4 1\no x1\nf 3 7 6 2\n";
    std::fs::write(dir.join("cube.obj"), obj).expect("obj");
    std::fs::write(
        dir.join("cube.mtl"),
        format!("newmtl wall\nKd 0.5 0.5 0.5\nKe 1 1 1\n{extra}"),
    )
    .expect("mtl");
    dir.join("cube.obj").to_string_lossy().into_owned()
}

/// `F` from the patches of object `a` on side `back` to those of object `b` on the same
/// side, area-weighted: `sum_i A_i sum_j F_ij / A_a`.
fn object_factor(s: &Scene, p: &PatchSet, ff: &FormFactors, a: &str, b: &str) -> f64 {
    let pick = |name: &str, i: usize| {
        s.objects[p.object[i] as usize] == name && s.faces[p.face[i] as usize].back
    };
    let (mut num, mut area) = (0.0, 0.0);
    for i in (0..p.len()).filter(|&i| pick(a, i)) {
        area += p.area[i];
        for j in (0..p.len()).filter(|&j| pick(b, j)) {
            num += p.area[i] * ff.get(i, j);
        }
    }
    num / area
}

#[test]
fn outward_cube_made_two_sided_gives_the_closed_forms_inside() {
    let dir = temp_dir("closed");
    let path = outward_cube(&dir, "");
    let mut scene = Scene::load(&path).expect("scene");
    assert_eq!(scene.faces.len(), 6);
    assert_eq!(scene.make_two_sided(true), 6);
    assert_eq!(scene.make_two_sided(true), 0, "twice changes nothing");
    let patches = PatchSet::build(&scene, Resolution::MaxEdge(0.25)).expect("patches");
    assert_eq!(patches.len(), 2 * 6 * 16);
    // Every patch has its twin, lying on it with the opposite normal.
    for i in 0..patches.len() {
        let t = patches.twin_of(i).expect("twin");
        assert_eq!(patches.twin_of(t), Some(i));
        assert_eq!(patches.normal[t], -patches.normal[i]);
        assert_eq!(patches.centroid[t], patches.centroid[i]);
    }
    let semi = EstimatorChoice::SemiAnalytic {
        points: 3,
        rays: 2,
        replicates: 4,
        tol: 1e-9,
    };
    let (ff, _, _) = pipeline::form_factors(&patches, &semi, 1, &Quiet).expect("factors");
    for (a, b, exact) in [
        ("z0", "z1", F_PARALLEL),
        ("x0", "x1", F_PARALLEL),
        ("z0", "y1", F_PERPENDICULAR),
        ("x1", "y0", F_PERPENDICULAR),
    ] {
        let f = object_factor(&scene, &patches, &ff, a, b);
        eprintln!("two-sided outward cube: F({a} -> {b}) = {f:.12} (exact {exact})");
        assert!((f - exact).abs() < 1e-7, "{a} -> {b}: {f} vs {exact}");
    }
    for i in 0..patches.len() {
        let s: f64 = (0..patches.len()).map(|j| ff.get(i, j)).sum();
        if scene.faces[patches.face[i] as usize].back {
            assert!((s - 1.0).abs() < 1e-7, "inner side {i}: row sum {s}");
        } else {
            assert!(ff.row_is_empty(i), "outer side {i} sees {s}");
        }
    }
    // First-hit estimators meet both sides of a face at one distance: a ray that meets
    // the outer side's back has met the inner side's front. Without that, about half the
    // rays would be lost and the rows would sum to about 1/2.
    let hemi = EstimatorChoice::Hemisphere {
        strata: 16,
        replicates: 4,
    };
    let (ff, _, _) = pipeline::form_factors(&patches, &hemi, 3, &Quiet).expect("factors");
    let inner: Vec<usize> = (0..patches.len())
        .filter(|&i| scene.faces[patches.face[i] as usize].back)
        .collect();
    let mean: f64 = inner
        .iter()
        .map(|&i| (0..patches.len()).map(|j| ff.get(i, j)).sum::<f64>())
        .sum::<f64>()
        / inner.len() as f64;
    eprintln!("hemisphere, inner sides: mean row sum {mean:.6}");
    assert!((mean - 1.0).abs() < 1e-3, "mean row sum {mean}");
    let f = object_factor(&scene, &patches, &ff, "z0", "z1");
    assert!((f - F_PARALLEL).abs() < 0.01, "hemisphere z0 -> z1: {f}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_mtl_line_and_the_flag_make_the_furnace_two_sided() {
    let dir = temp_dir("furnace");
    // The MTL's `#@two-sided` and `--two-sided` make the same faces.
    let with_line = Scene::load(&outward_cube(&dir, "#@two-sided\n")).expect("scene");
    assert_eq!(with_line.faces.len(), 12);
    assert!(with_line.materials[0].two_sided);
    let path = outward_cube(&dir, "");
    let flagged = pipeline::load_scene(&path, true).expect("scene");
    assert_eq!(flagged.faces, with_line.faces);
    // The furnace: inside B = E / (1 - rho) = 2, outside (sees nothing) B = E = 1.
    let cfg = BakeConfig {
        scene: path.clone(),
        out_dir: dir.join("out"),
        resolution: Resolution::MaxEdge(0.5),
        preview: (16, 16),
        two_sided: true,
        ..BakeConfig::default()
    };
    let s = pipeline::bake(&cfg, &Quiet).expect("bake");
    assert!(
        !s.warnings
            .iter()
            .any(|w| w.contains("see nothing") || w.contains("point out")),
        "{:?}",
        s.warnings
    );
    let bake = radiosity::output::read_exr(&dir.join("out/radiosity.exr")).expect("exr");
    let (mut inside, mut outside) = (0, 0);
    for (n, c) in bake.normals.iter().zip(&bake.rgb) {
        let p = bake.positions[inside + outside];
        // Inward normals point toward the centre.
        let toward = (glam::Vec3::splat(0.5) - p).dot(*n) > 0.0;
        let want = if toward { 2.0 } else { 1.0 };
        assert!((c[0] - want).abs() < 1e-5, "{p} {n}: {c:?}");
        if toward {
            inside += 1
        } else {
            outside += 1
        }
    }
    assert!(inside > 0 && outside > 0);
    // Bad `#@two-sided` lines name their line.
    std::fs::write(
        dir.join("bad.mtl"),
        "newmtl wall\nKe 1 1 1\n#@two-sided yes\n",
    )
    .unwrap();
    std::fs::write(
        dir.join("bad.obj"),
        "mtllib bad.mtl\nusemtl wall\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    )
    .unwrap();
    let e = Scene::load(dir.join("bad.obj").to_str().unwrap())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("bad.mtl:3") && e.contains("takes no value"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Records the observer's events in order.
#[derive(Default)]
struct Log(Mutex<Vec<String>>);

impl Observer for Log {
    fn warn(&self, msg: &str) {
        self.0.lock().unwrap().push(format!("warn {msg}"));
    }
    fn begin(&self, stage: &str, _total: u64) {
        self.0.lock().unwrap().push(format!("begin {stage}"));
    }
}

#[test]
fn an_outward_room_is_warned_about_before_any_form_factor_and_hierarchy_refuses_it() {
    let dir = temp_dir("early");
    let path = outward_cube(&dir, "");
    let cfg = BakeConfig {
        scene: path.clone(),
        out_dir: dir.join("out"),
        resolution: Resolution::MaxEdge(0.5),
        preview: (16, 16),
        ..BakeConfig::default()
    };
    let log = Log::default();
    let s = pipeline::bake(&cfg, &log).expect("bake");
    let events = log.0.into_inner().unwrap();
    let warned = events
        .iter()
        .position(|e| e.starts_with("warn") && e.contains("--two-sided"))
        .unwrap_or_else(|| panic!("no early warning: {events:?}"));
    let ff = events
        .iter()
        .position(|e| e == "begin form factors")
        .expect("form factors ran");
    assert!(warned < ff, "{events:?}");
    assert!(s.warnings.iter().any(|w| w.contains("point out of it")));
    // The cube wound inward is not warned about, and neither is the Cornell box.
    for scene in ["cube", "cornell"] {
        let s = Scene::load(scene).unwrap();
        assert_eq!(s.inside_out_warning(), None, "{scene}");
    }
    // Hierarchical radiosity refuses two-sided faces before any work.
    let h = BakeConfig {
        two_sided: true,
        out_dir: dir.join("hier"),
        hierarchy: Some(radiosity::hierarchy::Settings::default()),
        ..cfg
    };
    // Refused before any stage after loading, and no folder written.
    let refused = |cfg: &BakeConfig| {
        let log = Log::default();
        let e = pipeline::bake(cfg, &log).unwrap_err().to_string();
        let events = log.0.into_inner().unwrap();
        assert!(
            !events
                .iter()
                .any(|e| e.starts_with("begin") && e != "begin load"),
            "{events:?}"
        );
        assert!(!cfg.out_dir.exists());
        e
    };
    let e = refused(&h);
    assert!(
        e.contains("--method hierarchical does not support two-sided faces")
            && e.contains("--two-sided was given"),
        "{e}"
    );
    // One-sided, the outward room is refused by the hierarchical method before any work
    // (its remedy there is flipping the normals: it would bake unlit), with no folder.
    let h1 = BakeConfig {
        two_sided: false,
        out_dir: dir.join("hier1"),
        ..h
    };
    let e = refused(&h1);
    assert!(
        e.contains("point out of it") && e.contains("flip the") && e.contains(&path),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn patches_that_see_nothing_are_told_about_two_sided_faces() {
    // An open scene (no room to probe): a plate facing down under a lamp facing down. The
    // plate sees nothing; the late warning names both fixes. Two-sided, the plate's back
    // sees the lamp, the lamp's back sees nothing but its front does: no warning.
    let dir = temp_dir("blind");
    std::fs::write(
        dir.join("m.mtl"),
        "newmtl plate\nKd 0.5 0.5 0.5\nnewmtl lamp\nKe 1 1 1\n",
    )
    .unwrap();
    std::fs::write(
        dir.join("p.obj"),
        "mtllib m.mtl\nusemtl plate\nv 0 0 0\nv 1 0 0\nv 1 0 1\nv 0 0 1\nf 1 2 3 4\n\
         usemtl lamp\nv 0.4 1 0.4\nv 0.6 1 0.4\nv 0.6 1 0.6\nv 0.4 1 0.6\nf 5 6 7 8\n",
    )
    .unwrap();
    let cfg = BakeConfig {
        scene: dir.join("p.obj").to_string_lossy().into_owned(),
        out_dir: dir.join("out"),
        resolution: Resolution::MaxEdge(0.25),
        preview: (16, 16),
        ..BakeConfig::default()
    };
    let s = pipeline::bake(&cfg, &Quiet).expect("bake");
    assert!(
        s.warnings.iter().any(|w| w.contains("see nothing")
            && w.contains("--two-sided")
            && w.contains("flip them")),
        "{:?}",
        s.warnings
    );
    assert!(!s.warnings.iter().any(|w| w.contains("point out of it")));
    let s = pipeline::bake(
        &BakeConfig {
            two_sided: true,
            ..cfg
        },
        &Quiet,
    )
    .expect("bake");
    assert!(
        !s.warnings.iter().any(|w| w.contains("see nothing")),
        "{:?}",
        s.warnings
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// The unit cube wound inward with a rug, a square `[0.25, 0.75]²` of another object, lying
/// on its floor `z = 0` and facing the same way; `two_sided` adds `#@two-sided` to the MTL.
fn cube_with_rug(dir: &std::path::Path, two_sided: bool) -> String {
    let obj = "mtllib cube.mtl\nusemtl wall\n\
        v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\nv 1 1 1\nv 0 1 1\n\
        o z0\nf 1 2 3 4\no z1\nf 5 8 7 6\no y0\nf 1 5 6 2\no y1\nf 4 3 7 8\n\
        o x0\nf 1 4 8 5\no x1\nf 2 6 7 3\n\
        v 0.25 0.25 0\nv 0.75 0.25 0\nv 0.75 0.75 0\nv 0.25 0.75 0\no rug\nf 9 10 11 12\n";
    std::fs::write(dir.join("cube.obj"), obj).expect("obj");
    let flag = if two_sided { "#@two-sided\n" } else { "" };
    std::fs::write(
        dir.join("cube.mtl"),
        format!("newmtl wall\n{flag}Kd 0.5 0.5 0.5\nKe 1 1 1\n"),
    )
    .expect("mtl");
    dir.join("cube.obj").to_string_lossy().into_owned()
}

/// A face lying on another and facing the same way (a rug on the floor) would receive the
/// light of the place it covers a second time: rows of the closed cube would sum to
/// `1 + F(wall -> rug)`, and the floor under the rug would see the room through it. Raised
/// off the floor, the rug covers it: every row of the closed room sums to 1 (the
/// enclosure rule) within its bar, and the floor under the rug sees nothing. Both with
/// one-sided faces and with two-sided ones.
#[test]
fn a_rug_lying_on_the_floor_covers_it_and_the_room_stays_closed() {
    for two_sided in [false, true] {
        let dir = temp_dir(if two_sided { "rug2" } else { "rug1" });
        let path = cube_with_rug(&dir, two_sided);
        let scene = pipeline::load_scene(&path, false).expect("scene");
        let raised: Vec<&String> = scene
            .warnings
            .iter()
            .filter(|w| w.contains("lay on other faces facing the same way"))
            .collect();
        assert_eq!(raised.len(), 1, "{:?}", scene.warnings);
        // Two-sided, the rug's underside lies on the floor's outside, which nothing sees:
        // only the rug's top is raised.
        assert!(raised[0].contains("1 face(s)"), "{}", raised[0]);
        let patches = PatchSet::build(&scene, Resolution::MaxEdge(0.25)).expect("patches");
        let semi = EstimatorChoice::SemiAnalytic {
            points: 4,
            rays: 4,
            replicates: 8,
            tol: 1e-9,
        };
        let (ff, _, _) = pipeline::form_factors(&patches, &semi, 7, &Quiet).expect("factors");
        // The sides facing into the room: the faces as written (the backs face out).
        let inside = |i: usize| !scene.faces[patches.face[i] as usize].back;
        let rug = |i: usize| scene.objects[patches.object[i] as usize] == "rug";
        let c = patches.centroid.clone();
        let under_rug = |i: usize| {
            !rug(i)
                && c[i].z.abs() < 1e-9
                && (0.25..0.75).contains(&c[i].x)
                && (0.25..0.75).contains(&c[i].y)
        };
        let (mut rows, mut worst) = (0, 0.0f64);
        for i in (0..patches.len()).filter(|&i| inside(i)) {
            let s = ff.row_sum(i);
            if under_rug(i) {
                assert!(s < 0.01, "floor patch {i} under the rug sees {s}");
                continue;
            }
            // 4 standard errors over at most 100 rows: a chance failure is below 1%.
            let bar = ff.row_sum_bar(i);
            let gap = (s - 1.0).abs();
            assert!(
                gap <= 4.0 * bar.se + bar.bound + 2e-3,
                "two-sided {two_sided}: row {i} sums to {s} ({bar:?})"
            );
            worst = worst.max(gap);
            rows += 1;
        }
        eprintln!(
            "rug on the floor (two-sided {two_sided}): {rows} rows, worst |sum - 1| {worst:.2e}"
        );
        assert!(rows >= 5 * 16 + 4, "{rows}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
