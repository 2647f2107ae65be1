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
    store::write(&honest, &patches, &ff, Repair::None, store::Format::Mtx).expect("write");
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
    let (sum, se) = (ff.row_sum(7), ff.row_sum_bar(7).magnitude());
    let target = 1.0 + (12.0 * se).max(0.01);
    assert!(sum > 0.5 && target < 1.5, "row 7: {sum} ± {se}");
    for v in &mut ff.f.data_mut()[lo..hi] {
        *v *= target / sum;
        assert!(*v <= 1.0);
    }
    let bad = dir.join("bad");
    store::write(&bad, &patches, &ff, Repair::None, store::Format::Mtx).expect("write");
    let err = bake(&bad, Repair::None, "bad-bake")
        .expect_err("a row over 1 must be refused")
        .to_string();
    assert!(
        err.contains("F.mtx") && err.contains("patch 7") && err.contains("--repair closure"),
        "{err}"
    );
    assert!(!dir.join("bad-bake").exists(), "nothing written");
    // The same matrix in npz: refused the same way, naming its file.
    let bad_npz = dir.join("bad-npz");
    store::write(&bad_npz, &patches, &ff, Repair::None, store::Format::Npz).expect("write");
    let err = bake(&bad_npz, Repair::None, "bad-npz-bake")
        .expect_err("a row over 1 must be refused")
        .to_string();
    assert!(err.contains("F.npz") && err.contains("patch 7"), "{err}");
    // Reciprocity alone does not restore row sums: still refused; closure is accepted.
    assert!(bake(&bad, Repair::Reciprocity, "bad-recip").is_err());
    bake(&bad, Repair::Closure, "bad-closure").expect("repaired rows are accepted");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `factors` into `dir` in `format`, with the area estimator (rows within their bars, so
/// bakes accept the folder).
fn factors_in(dir: &std::path::Path, patches: usize, seed: u64, format: store::Format) {
    let est = EstimatorChoice::AreaStratified {
        strata: 4,
        replicates: 2,
    };
    pipeline::factors_within(
        "cornell",
        Resolution::Patches(patches),
        &est,
        seed,
        dir,
        Repair::None,
        format,
        None,
        false,
        &Quiet,
    )
    .expect("factors");
}

#[test]
fn factors_round_trip_through_npz_and_bake_from_it() {
    let dir = temp_dir("npz");
    let scene = Scene::load("cornell").expect("scene");
    let patches = PatchSet::build(&scene, Resolution::Patches(80)).expect("patches");
    let text = dir.join("mtx");
    factors_in(&text, 80, 9, store::Format::Mtx);
    let want = store::read(&text, &patches).expect("mtx folder");
    for (format, name) in [
        (store::Format::Npz, "npz"),
        (store::Format::NpzDeflated, "deflated"),
    ] {
        let d = dir.join(name);
        factors_in(&d, 80, 9, format);
        for f in ["F.npz", "stderr.npz", "patches.csv", "provenance.json"] {
            assert!(d.join(f).exists(), "{name}: {f} missing");
        }
        assert!(!d.join("F.mtx").exists() && !d.join("stderr.mtx").exists());
        radiosity::output::Manifest::read(&d)
            .and_then(|m| m.verify(&d))
            .expect("a whole folder");
        let back = store::read(&d, &patches).expect("read back");
        assert_eq!(back.f.indptr(), want.f.indptr());
        assert_eq!(back.f.indices(), want.f.indices());
        assert_eq!(
            back.f.data(),
            want.f.data(),
            "{name}: the text's values, bit for bit"
        );
        assert_eq!(back.se, want.se);
        assert_eq!(back.estimator, want.estimator);
        let bake = pipeline::bake(
            &BakeConfig {
                out_dir: dir.join(format!("bake-{name}")),
                resolution: Resolution::Patches(80),
                preview: (32, 32),
                factors: Some(d.clone()),
                ..BakeConfig::default()
            },
            &Quiet,
        )
        .expect("bake from npz factors");
        assert_eq!(
            bake.stage_seconds("form factors"),
            0.0,
            "no rays may be cast"
        );
    }
    // The default writes text for a matrix this small.
    let auto = dir.join("auto");
    factors_in(&auto, 80, 9, store::Format::Auto);
    assert!(auto.join("F.mtx").exists() && !auto.join("F.npz").exists());
    assert_eq!(
        store::Format::Auto.resolve(store::AUTO_NPZ_ENTRIES),
        store::Format::Mtx
    );
    assert_eq!(
        store::Format::Auto.resolve(store::AUTO_NPZ_ENTRIES + 1),
        store::Format::Npz
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_tampered_truncated_or_unphysical_npz_is_refused() {
    let dir = temp_dir("npz-bad");
    let scene = Scene::load("cornell").expect("scene");
    let patches = PatchSet::build(&scene, Resolution::Patches(60)).expect("patches");
    let n = patches.len();
    let (a, b) = (dir.join("a"), dir.join("b"));
    factors_in(&a, 60, 1, store::Format::Npz);
    factors_in(&b, 60, 2, store::Format::Npz);
    let good = store::read(&a, &patches).expect("the folder as written");
    let restore = || {
        for f in ["F.npz", "stderr.npz", "provenance.json"] {
            let _ = std::fs::remove_file(a.join(f));
        }
        factors_in(&a, 60, 1, store::Format::Npz);
    };
    let refused = |want: &[&str]| {
        let e = store::read(&a, &patches)
            .expect_err("must be refused")
            .to_string();
        for w in want {
            assert!(e.contains(w), "expected `{w}` in: {e}");
        }
        e
    };

    // Another seed's matrix (valid, same size): the hash names the file.
    std::fs::copy(b.join("F.npz"), a.join("F.npz")).expect("copy");
    refused(&["F.npz", "SHA-256"]);
    restore();

    // Truncated, at several lengths: named, never a panic; through the command line the
    // bake exits with status 1 and the message.
    let bytes = std::fs::read(a.join("F.npz")).expect("F.npz");
    for len in [
        0,
        10,
        100,
        bytes.len() / 2,
        bytes.len() - 23,
        bytes.len() - 1,
    ] {
        std::fs::write(a.join("F.npz"), &bytes[..len]).expect("write");
        let e = refused(&["F.npz"]);
        assert!(
            e.contains("truncated") || e.contains("not a zip"),
            "{len}: {e}"
        );
    }
    let out = Command::new(env!("CARGO_BIN_EXE_radiosity"))
        .args([
            "bake",
            "cornell",
            "--patches",
            "60",
            "--size",
            "32x32",
            "--factors",
        ])
        .arg(&a)
        .arg("-o")
        .arg(dir.join("cli-bake"))
        .output()
        .expect("binary runs");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("F.npz") && stderr.contains("truncated"),
        "{stderr}"
    );
    std::fs::write(a.join("F.npz"), &bytes).expect("write");
    store::read(&a, &patches).expect("the original bytes back");

    // Well-formed npz files with what a folder may not hold (their hashes are not checked
    // before the values: the value is the clearer message).
    let ptr = good.f.indptr();
    let ptr = ptr.to_proper();
    let (ind, data) = (good.f.indices(), good.f.data());
    let write_f = |data: &[f64]| {
        radiosity::npz::write(
            &a.join("F.npz"),
            n,
            &ptr,
            ind,
            data,
            radiosity::npz::Compression::Stored,
        )
        .expect("write F.npz")
    };
    let mut over = data.to_vec();
    over[5] = 1.5;
    write_f(&over);
    refused(&[
        "F.npz",
        "data.npy: entry 5",
        "is 1.5",
        "a form factor lies in [0, 1]",
    ]);
    over[5] = f64::NAN;
    write_f(&over);
    refused(&["F.npz", "is NaN"]);
    write_f(data);
    store::read(&a, &patches).expect("the same values, the same bytes, the same hash");
    let write_se = |se: &[f32], ind: &[u32]| {
        radiosity::npz::write(
            &a.join("stderr.npz"),
            n,
            &ptr,
            ind,
            se,
            radiosity::npz::Compression::Stored,
        )
        .expect("write stderr.npz")
    };
    // The standard errors as stderr.npz holds them: entries with a bound (near pairs
    // integrated by quadrature) are held in memory as negative bars and stored as 0 here.
    let plain: Vec<f32> = good.se.iter().map(|&s| s.max(0.0)).collect();
    let mut se = plain.clone();
    se[3] = -1e-3;
    write_se(&se, ind);
    refused(&["stderr.npz", "is -0.001", "finite and >= 0"]);
    se[3] = f32::INFINITY;
    write_se(&se, ind);
    refused(&["stderr.npz", "is inf"]);
    // Another pattern: the last entry of a row moved to the last column (still increasing).
    let mut other = ind.to_vec();
    let row = (0..n)
        .find(|&i| ptr[i + 1] > ptr[i] && (other[ptr[i + 1] - 1] as usize) < n - 1)
        .expect("a row whose last entry is not in the last column");
    other[ptr[row + 1] - 1] = n as u32 - 1;
    write_se(&plain, &other);
    refused(&["stderr.npz", "do not have the pattern of F.npz"]);
    // Float64 standard errors are not what the folder stores.
    let se64: Vec<f64> = plain.iter().map(|&s| s as f64).collect();
    radiosity::npz::write(
        &a.join("stderr.npz"),
        n,
        &ptr,
        ind,
        &se64,
        radiosity::npz::Compression::Stored,
    )
    .expect("write");
    refused(&["stderr.npz", "data.npy: dtype '<f8', expected '<f4'"]);
    restore();

    // A provenance naming no matrix files, or both layouts.
    let prov = std::fs::read_to_string(a.join("provenance.json")).expect("provenance");
    std::fs::write(
        a.join("provenance.json"),
        prov.replace("\"F.npz\"", "\"G.npz\""),
    )
    .expect("w");
    refused(&[
        "provenance.json",
        "expected F.mtx and stderr.mtx, or F.npz and stderr.npz",
    ]);
    let both = prov.replacen(
        "\"patches.csv\"",
        "\"F.mtx\": \"0\",\n    \"stderr.mtx\": \"0\",\n    \"patches.csv\"",
        1,
    );
    std::fs::write(a.join("provenance.json"), both).expect("w");
    refused(&["provenance.json", "F.mtx, F.npz"]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_factors_command_writes_npz_on_request() {
    let dir = temp_dir("npz-cli");
    let run = |format: &str, out: &str| {
        Command::new(env!("CARGO_BIN_EXE_radiosity"))
            .args([
                "factors",
                "cornell",
                "--patches",
                "60",
                "--estimator",
                "stratified",
            ])
            .args(["--format", format, "-o"])
            .arg(dir.join(out))
            .output()
            .expect("binary runs")
    };
    let out = run("npz", "npz");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        stdout.contains("F.npz") && stdout.contains("stderr.npz"),
        "{stdout}"
    );
    assert!(dir.join("npz/F.npz").exists() && !dir.join("npz/F.mtx").exists());
    let out = run("csv", "csv");
    assert_eq!(
        out.status.code(),
        Some(2),
        "an unknown layout is a usage error"
    );
    assert!(String::from_utf8_lossy(&out.stderr).contains("npz-deflated"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn scipy_reads_from_npz_the_matrix_mmread_reads_from_text() {
    // `scripts/check-npz.py` under RADIOSITY_PYTHON (default python3), when it has NumPy
    // and SciPy; otherwise the test says why it does nothing.
    let python = std::env::var("RADIOSITY_PYTHON").unwrap_or_else(|_| "python3".into());
    match Command::new(&python)
        .args(["-c", "import numpy, scipy.sparse, scipy.io"])
        .output()
    {
        Ok(o) if o.status.success() => {}
        Ok(o) => {
            eprintln!(
                "skipped: {python} has no NumPy and SciPy ({}); set RADIOSITY_PYTHON to a \
                 Python that has them",
                String::from_utf8_lossy(&o.stderr)
                    .lines()
                    .last()
                    .unwrap_or("")
            );
            return;
        }
        Err(e) => {
            eprintln!("skipped: no {python} to run ({e}); set RADIOSITY_PYTHON");
            return;
        }
    }
    let dir = temp_dir("scipy");
    factors_in(&dir.join("mtx"), 120, 4, store::Format::Mtx);
    factors_in(&dir.join("npz"), 120, 4, store::Format::Npz);
    factors_in(&dir.join("deflated"), 120, 4, store::Format::NpzDeflated);
    factors_in(&dir.join("other"), 120, 5, store::Format::Npz);
    let check = |npz: &str| {
        Command::new(&python)
            .arg(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/check-npz.py"))
            .arg(dir.join(npz))
            .arg(dir.join("mtx"))
            .output()
            .expect("python runs")
    };
    for npz in ["npz", "deflated"] {
        let out = check(npz);
        let stdout = String::from_utf8_lossy(&out.stdout);
        eprint!("{stdout}");
        assert!(
            out.status.success(),
            "{npz}: {stdout}{}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert_eq!(stdout.matches("bit for bit").count(), 2, "{stdout}");
    }
    // Another seed's matrix differs, and the script says so.
    let out = check("other");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{stdout}");
    assert!(stdout.contains("F.npz vs F.mtx: DIFFERENT"), "{stdout}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The semi-analytic estimator on the Cornell box makes both kinds of bar: bounds on the
/// pairs nothing can block, standard errors on the others. Both layouts keep them apart
/// (`stderr` and `bound`, each 0 where the other holds) and read them back bit for bit; a
/// folder without a `bound` file (written before bounds were told apart) reads its
/// `stderr` as standard errors.
#[test]
fn bounds_and_standard_errors_round_trip_apart() {
    use radiosity::matrix::Bar;
    let est = EstimatorChoice::SemiAnalytic {
        points: 2,
        rays: 2,
        replicates: 4,
        tol: 1e-6,
    };
    let scene = Scene::load("cornell").expect("scene");
    let patches = PatchSet::build(&scene, Resolution::Patches(80)).expect("patches");
    let (ff, _, _) = pipeline::form_factors(&patches, &est, 3, &Quiet).expect("factors");
    let bars: Vec<Bar> = ff.se.iter().map(|&s| Bar::of(s)).collect();
    let bounded = bars.iter().filter(|b| b.bound > 0.0).count();
    let random = bars.iter().filter(|b| b.se > 0.0).count();
    assert!(
        bounded > 100 && random > 100,
        "{bounded} bounds, {random} errors"
    );
    for format in [store::Format::Mtx, store::Format::Npz] {
        let dir = temp_dir(&format!("bounds-{format:?}"));
        pipeline::factors_within(
            "cornell",
            Resolution::Patches(80),
            &est,
            3,
            &dir,
            Repair::None,
            format,
            None,
            false,
            &Quiet,
        )
        .expect("factors");
        let back = store::read(&dir, &patches).expect("read back");
        assert_eq!(back.f.data(), ff.f.data(), "{format:?}");
        assert_eq!(back.se, ff.se, "{format:?}");
        if format == store::Format::Mtx {
            let text = std::fs::read_to_string(dir.join("bound.mtx")).expect("bound.mtx");
            assert!(text.lines().nth(2).unwrap().contains("add linearly"));
            // Without its bound file (and its hash), the folder is an older one: the
            // bounded entries read as standard error 0.
            std::fs::remove_file(dir.join("bound.mtx")).expect("remove");
            let prov = dir.join("provenance.json");
            let mut json: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(&prov).expect("read")).unwrap();
            json["sha256"].as_object_mut().unwrap().remove("bound.mtx");
            std::fs::write(&prov, serde_json::to_string_pretty(&json).unwrap()).unwrap();
            let old = store::read(&dir, &patches).expect("an older folder reads");
            for (a, b) in old.se.iter().zip(&ff.se) {
                let want = if b.is_sign_negative() { 0.0 } else { *b };
                assert_eq!(*a, want);
            }
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
