//! The reusable factors folder: written by `factors`, reused by `bake --factors`, refused
//! for other geometry.

use std::process::Command;

use radiosity::mesh::{PatchSet, Resolution};
use radiosity::pipeline::{self, BakeConfig, EstimatorChoice, Quiet};
use radiosity::repair::Repair;
use radiosity::scene::Scene;
use radiosity::store;

fn temp_dir(tag: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("radiosity-store-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

#[test]
fn factors_round_trip_through_matrix_market() {
    let dir = temp_dir("roundtrip");
    let est = EstimatorChoice::AreaStratified {
        strata: 4,
        replicates: 2,
    };
    let s = pipeline::factors(
        "cornell",
        Resolution::Patches(80),
        &est,
        9,
        &dir,
        Repair::None,
        &Quiet,
    )
    .expect("factors");
    for f in ["F.mtx", "stderr.mtx", "patches.csv", "provenance.json"] {
        assert!(dir.join(f).exists(), "{f} missing");
    }
    let scene = Scene::load("cornell").expect("scene");
    let patches = PatchSet::build(&scene, Resolution::Patches(80)).expect("patches");
    assert_eq!(s.provenance.patches, patches.len());
    let (ff, _, _) = pipeline::form_factors(&patches, &est, 9, &Quiet).expect("recompute");
    let back = store::read(&dir, &patches).expect("read back");
    assert_eq!(back.f.indptr(), ff.f.indptr());
    assert_eq!(back.f.indices(), ff.f.indices());
    // Written with `{:e}` (shortest round-trip form): values come back bit for bit.
    assert_eq!(back.f.data(), ff.f.data());
    assert_eq!(back.se, ff.se);
    let csv = std::fs::read_to_string(dir.join("patches.csv")).expect("csv");
    assert_eq!(csv.lines().count(), patches.len() + 1);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bake_reuses_factors_and_refuses_other_geometry() {
    let dir = temp_dir("reuse");
    let factors = dir.join("factors");
    let est = EstimatorChoice::AreaStratified {
        strata: 4,
        replicates: 2,
    };
    pipeline::factors(
        "cornell",
        Resolution::Patches(80),
        &est,
        3,
        &factors,
        Repair::None,
        &Quiet,
    )
    .expect("factors");
    let reuse = BakeConfig {
        out_dir: dir.join("bake"),
        resolution: Resolution::Patches(80),
        estimator: est.clone(),
        seed: 3,
        preview: (32, 32),
        factors: Some(factors.clone()),
        ..BakeConfig::default()
    };
    let with = pipeline::bake(&reuse, &Quiet).expect("bake with stored factors");
    assert_eq!(
        with.stage_seconds("form factors"),
        0.0,
        "no rays may be cast"
    );
    let fresh = pipeline::bake(
        &BakeConfig {
            factors: None,
            ..reuse.clone()
        },
        &Quiet,
    )
    .expect("bake computing factors");
    let (a, b) = (
        radiosity::output::read_exr(&dir.join("bake/radiosity.exr")).expect("exr"),
        fresh.vertices,
    );
    assert_eq!(a.vertex_count, b);

    // Other subdivision: refused, naming the folder and the patch counts.
    let other = BakeConfig {
        resolution: Resolution::Patches(200),
        ..reuse.clone()
    };
    let err = pipeline::bake(&other, &Quiet)
        .expect_err("mismatch must be refused")
        .to_string();
    assert!(
        err.contains("provenance.json") && err.contains("patches"),
        "{err}"
    );

    // Other scene through the command line: refused with exit status 1.
    let out = Command::new(env!("CARGO_BIN_EXE_radiosity"))
        .args([
            "bake",
            "cube",
            "--patches",
            "80",
            "--size",
            "32x32",
            "--factors",
        ])
        .arg(&factors)
        .arg("-o")
        .arg(dir.join("cube"))
        .output()
        .expect("binary runs");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("factors were computed for"), "{stderr}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_folder_with_another_runs_files_is_refused() {
    let dir = temp_dir("mixed");
    let est = EstimatorChoice::AreaStratified {
        strata: 3,
        replicates: 2,
    };
    let run = |seed: u64, name: &str| {
        let out = dir.join(name);
        pipeline::factors(
            "cornell",
            Resolution::Patches(60),
            &est,
            seed,
            &out,
            Repair::None,
            &Quiet,
        )
        .expect("factors");
        out
    };
    let (a, b) = (run(1, "a"), run(2, "b"));
    radiosity::output::Manifest::read(&a)
        .and_then(|m| m.verify(&a))
        .expect("a whole folder");
    let scene = Scene::load("cornell").expect("scene");
    let patches = PatchSet::build(&scene, Resolution::Patches(60)).expect("patches");
    store::read(&a, &patches).expect("the folder as written");

    // Same geometry and patch count, another seed's matrix: refused, naming the file.
    for f in ["F.mtx", "stderr.mtx"] {
        std::fs::copy(b.join(f), a.join(f)).expect("copy");
    }
    let err = store::read(&a, &patches)
        .expect_err("mixed folder")
        .to_string();
    assert!(err.contains("F.mtx") && err.contains("SHA-256"), "{err}");

    // An edited value (doubled, still in [0, 1]) is refused the same way.
    std::fs::copy(b.join("stderr.mtx"), a.join("stderr.mtx")).expect("copy");
    let text = std::fs::read_to_string(b.join("F.mtx")).expect("F.mtx");
    let mut lines: Vec<String> = text.lines().map(String::from).collect();
    let k = lines.iter().position(|l| !l.starts_with('%')).unwrap() + 1;
    let w: Vec<&str> = lines[k].split(' ').collect();
    let doubled = w[2].parse::<f64>().unwrap() * 2.0;
    lines[k] = format!("{} {} {doubled:e}", w[0], w[1]);
    std::fs::write(a.join("F.mtx"), lines.join("\n") + "\n").expect("write");
    let err = store::read(&a, &patches)
        .expect_err("edited value")
        .to_string();
    assert!(err.contains("F.mtx"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_stored_row_over_one_beyond_its_bar_is_refused_unless_repaired() {
    let dir = temp_dir("overone");
    let scene = Scene::load("cornell").expect("scene");
    let patches = PatchSet::build(&scene, Resolution::Patches(80)).expect("patches");
    let est = BakeConfig::default().estimator;
    let (mut ff, _, _) = pipeline::form_factors(&patches, &est, 5, &Quiet).expect("factors");
    // The honest folder is accepted (this is also what `bake_reuses_factors` relies on).
    let honest = dir.join("honest");
    store::write(&honest, &patches, &ff, Repair::None).expect("write");
    let bake = |factors: &std::path::Path, repair: Repair, out: &str| {
        pipeline::bake(
            &BakeConfig {
                out_dir: dir.join(out),
                resolution: Resolution::Patches(80),
                estimator: est.clone(),
                seed: 5,
                preview: (32, 32),
                factors: Some(factors.to_path_buf()),
                repair,
                ..BakeConfig::default()
            },
            &Quiet,
        )
    };
    bake(&honest, Repair::None, "honest-bake").expect("an honest folder is accepted");
    // Row 7 scaled to sum 1 + 12 of its standard errors (at least 1.01), every entry
    // still in [0, 1]: a valid, hashed folder whose physics is wrong.
    let (lo, hi) = (ff.f.indptr().index(7), ff.f.indptr().index(8));
    let (sum, se) = (ff.row_sum(7), ff.row_sum_stderr(7));
    let target = 1.0 + (12.0 * se).max(0.01);
    assert!(sum > 0.5 && target < 1.5, "row 7: {sum} ± {se}");
    for v in &mut ff.f.data_mut()[lo..hi] {
        *v *= target / sum;
        assert!(*v <= 1.0);
    }
    let bad = dir.join("bad");
    store::write(&bad, &patches, &ff, Repair::None).expect("write");
    let err = bake(&bad, Repair::None, "bad-bake")
        .expect_err("a row over 1 must be refused")
        .to_string();
    assert!(
        err.contains("F.mtx") && err.contains("patch 7") && err.contains("--repair closure"),
        "{err}"
    );
    assert!(!dir.join("bad-bake").exists(), "nothing written");
    // Reciprocity alone does not restore row sums: still refused; closure is accepted.
    assert!(bake(&bad, Repair::Reciprocity, "bad-recip").is_err());
    bake(&bad, Repair::Closure, "bad-closure").expect("repaired rows are accepted");
    let _ = std::fs::remove_dir_all(&dir);
}
