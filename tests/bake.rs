//! End to end: a Cornell box bake writes its three files, the EXR reads back exactly, and
//! the red and green walls bleed onto the white ones.

use radiosity::mesh::{PatchSet, Resolution};
use radiosity::output;
use radiosity::pipeline::{self, BakeConfig, Quiet};
use radiosity::scene::Scene;

fn temp_dir(tag: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("radiosity-test-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

#[test]
fn cornell_bake_writes_files_and_bleeds_colour() {
    let dir = temp_dir("bake");
    let cfg = BakeConfig {
        out_dir: dir.clone(),
        resolution: Resolution::Patches(400),
        preview: (96, 96),
        ..BakeConfig::default()
    };
    let summary = pipeline::bake(&cfg, &Quiet).expect("bake");
    assert!(summary.solve.converged);
    for f in ["radiosity.exr", "mesh.ply", "preview.png"] {
        let meta = std::fs::metadata(dir.join(f)).expect(f);
        assert!(meta.len() > 0, "{f} is empty");
    }
    let bake = output::read_exr(&dir.join("radiosity.exr")).expect("EXR reads back");
    assert_eq!(bake.scene, "cornell");
    assert_eq!(bake.rgb.len(), summary.vertices);
    assert!(bake
        .rgb
        .iter()
        .flatten()
        .all(|c| c.is_finite() && *c >= 0.0));

    // Colour bleeding: on the white back wall (z = 559.2), the red/green ratio is higher
    // next to the red wall (x near 556) than next to the green wall (x near 0).
    let ratio = |near_red: bool| {
        let (mut r, mut g) = (0.0f64, 0.0f64);
        for (p, c) in bake.positions.iter().zip(&bake.rgb) {
            let on_back = (p.z - 559.2).abs() < 1.0 && p.y > 50.0 && p.y < 500.0;
            let side = if near_red { p.x > 450.0 } else { p.x < 100.0 };
            if on_back && side {
                r += c[0] as f64;
                g += c[1] as f64;
            }
        }
        assert!(g > 0.0, "no back-wall vertices found");
        r / g
    };
    let (red_side, green_side) = (ratio(true), ratio(false));
    eprintln!("back wall R/G: near red wall {red_side:.3}, near green wall {green_side:.3}");
    assert!(
        red_side > 1.15 * green_side,
        "no visible bleeding: {red_side} vs {green_side}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn exr_round_trips_bit_for_bit() {
    let scene = Scene::load("cornell").expect("scene");
    let patches = PatchSet::build(&scene, Resolution::Patches(120)).expect("patches");
    let b: Vec<[f64; 3]> = (0..patches.len())
        .map(|i| {
            let r = patches.rho(i);
            [r[0] * 3.7 + i as f64 * 1e-3, r[1] / 7.0, r[2] + 1e5]
        })
        .collect();
    let verts = output::interpolate(&patches, &b, 30.0);
    let dir = temp_dir("exr");
    std::fs::create_dir_all(&dir).expect("temp dir");
    let path = dir.join("r.exr");
    output::write_exr(&path, &verts, "cornell").expect("write");
    let back = output::read_exr(&path).expect("read");
    assert_eq!(back.positions, verts.positions);
    assert_eq!(back.normals, verts.normals);
    assert_eq!(back.rgb, verts.rgb);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_room_with_outward_normals_is_warned_about_with_the_fix() {
    let dir = temp_dir("outward");
    std::fs::create_dir_all(&dir).expect("dir");
    // A unit box whose six faces wind outward (as Blender's default cube), and a small
    // lamp inside facing down: from inside, nothing is seen.
    let obj = "mtllib m.mtl\n\
        v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\nv 1 1 1\nv 0 1 1\n\
        v 0.4 0.9 0.4\nv 0.6 0.9 0.4\nv 0.6 0.9 0.6\nv 0.4 0.9 0.6\n\
        usemtl wall\n\
        f 1 4 3 2\nf 5 6 7 8\nf 1 2 6 5\nf 4 8 7 3\nf 1 5 8 4\nf 2 3 7 6\n\
        usemtl lamp\nf 9 10 11 12\n";
    std::fs::write(dir.join("room.obj"), obj).expect("obj");
    std::fs::write(
        dir.join("m.mtl"),
        "newmtl wall\nKd 0.5 0.5 0.5\nnewmtl lamp\nKe 1 1 1\n",
    )
    .expect("mtl");
    let cfg = BakeConfig {
        scene: dir.join("room.obj").to_string_lossy().into_owned(),
        out_dir: dir.join("out"),
        resolution: Resolution::Patches(200),
        preview: (16, 16),
        ..BakeConfig::default()
    };
    let s = pipeline::bake(&cfg, &Quiet).expect("bake");
    // Found before any form factor from the room's shell (see tests/two_sided.rs), with
    // both fixes.
    assert!(
        s.warnings.iter().any(|w| w.contains("point out of it")
            && w.contains("--two-sided")
            && w.contains("flip the normals")),
        "{:?}",
        s.warnings
    );
    // The same box winding inward: no such warning.
    let inward = obj.replace(
        "f 1 4 3 2\nf 5 6 7 8\nf 1 2 6 5\nf 4 8 7 3\nf 1 5 8 4\nf 2 3 7 6\n",
        "f 2 3 4 1\nf 8 7 6 5\nf 5 6 2 1\nf 3 7 8 4\nf 4 8 5 1\nf 6 7 3 2\n",
    );
    std::fs::write(dir.join("room.obj"), inward).expect("obj");
    let s = pipeline::bake(&cfg, &Quiet).expect("bake");
    assert!(
        !s.warnings
            .iter()
            .any(|w| w.contains("see nothing") || w.contains("point out of it")),
        "{:?}",
        s.warnings
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// `--method auto` (the default) bakes hierarchically unless the command line gives a
/// setting of the flat method's, or the scene has faces the hierarchy does not support;
/// `--method hierarchical` refuses those settings by name.
#[test]
fn the_default_method_is_hierarchical_unless_the_flat_one_is_asked_for() {
    let dir = temp_dir("method");
    std::fs::create_dir_all(&dir).expect("dir");
    let run = |args: &[&str], out: &str| {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_radiosity"))
            .args(["bake"])
            .args(args)
            .args(["--size", "16x16", "-o"])
            .arg(dir.join(out))
            .output()
            .expect("binary runs");
        let text =
            String::from_utf8_lossy(&o.stdout).into_owned() + &String::from_utf8_lossy(&o.stderr);
        assert!(!text.contains("panicked"), "{text}");
        (o.status.success(), text)
    };
    let coarse = ["--patches", "12", "--error", "0.2", "--max-passes", "2"];
    let (ok, text) = run(&[&["cube"][..], &coarse].concat(), "auto");
    assert!(ok && text.contains("baked `cube` hierarchically"), "{text}");
    for flat in [
        &["--estimator", "hemisphere"][..],
        &["--solver", "jacobi"],
        &["--repair", "closure"],
        &["--steps", "1"],
        &["--two-sided"],
        &["--method", "flat"],
    ] {
        let (ok, text) = run(&[&["cube", "--patches", "12"][..], flat].concat(), "flat");
        assert!(ok, "{flat:?}: {text}");
        assert!(
            text.contains("baked `cube`: ") && !text.contains("hierarchically"),
            "{flat:?}: {text}"
        );
    }
    for (flag, value) in [("--solver", "jacobi"), ("--estimator", "hemisphere")] {
        let (ok, text) = run(&["cube", "--method", "hierarchical", flag, value], "no");
        assert!(
            !ok && text.contains(&format!("{flag} sets the flat")),
            "{text}"
        );
    }
    // A two-sided material: flat, with a warning naming why.
    std::fs::write(
        dir.join("m.mtl"),
        "newmtl wall\nKd 0.5 0.5 0.5\n#@two-sided\nnewmtl lamp\nKe 1 1 1\n",
    )
    .expect("mtl");
    std::fs::write(
        dir.join("room.obj"),
        "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 1 0 1\nv 0 0 1\n\
         v 0.4 0.9 0.4\nv 0.6 0.9 0.4\nv 0.6 0.9 0.6\nv 0.4 0.9 0.6\n\
         usemtl wall\nf 1 4 3 2\nusemtl lamp\nf 5 6 7 8\n",
    )
    .expect("obj");
    let scene = dir.join("room.obj");
    let scene = scene.to_str().expect("utf-8 path");
    let (ok, text) = run(&[scene, "--patches", "12"], "two-sided");
    assert!(ok, "{text}");
    assert!(
        text.contains("baked with the flat method") && text.contains("two-sided"),
        "{text}"
    );
    let (ok, text) = run(&[scene, "--method", "hierarchical"], "refused");
    assert!(!ok && text.contains("does not support two-sided"), "{text}");
    let _ = std::fs::remove_dir_all(&dir);
}
