//! Runs under `mpirun` (built with the cargo feature `mpi`; `./dev test` builds it and
//! installs Open MPI): the factors folder of 1, 2 and 3 ranks is the one process's byte
//! for byte, the distributed bake's radiosity is the one process's, and a failing rank
//! ends the run with a message and no folder.
//!
//! The ranks run on this machine (`--oversubscribe`: 3 ranks on 2 cores are for
//! correctness, not speed). As root, mpirun needs `OMPI_ALLOW_RUN_AS_ROOT`; CMA single
//! copy is turned off because containers often forbid the `ptrace` it needs.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const BIN: &str = env!("CARGO_BIN_EXE_radiosity");

fn temp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("radiosity-mpi-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

/// `mpirun -np NP radiosity ARGS` with `env` added.
fn mpirun(np: usize, args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut c = Command::new("mpirun");
    c.args(["--oversubscribe", "-np", &np.to_string(), BIN])
        .args(args)
        .env("OMPI_ALLOW_RUN_AS_ROOT", "1")
        .env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
        .env("OMPI_MCA_btl_vader_single_copy_mechanism", "none");
    for (k, v) in env {
        c.env(k, v);
    }
    c.output()
        .expect("mpirun (Open MPI: apt-get install openmpi-bin libopenmpi-dev; ./dev test does)")
}

/// `radiosity ARGS` as one process, no mpirun.
fn single(args: &[&str]) -> Output {
    Command::new(BIN).args(args).output().expect("radiosity")
}

fn ok(out: &Output, what: &str) {
    assert!(
        out.status.success(),
        "{what}: {}\n{}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

fn bytes(p: &Path) -> Vec<u8> {
    std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// The acceptance test of the distributed form factors: the closed cube and the Cornell
/// box at their default settings (semi-analytic estimator), on 1, 2 and 3 ranks, write
/// the single process's `F.mtx` and `stderr.mtx` byte for byte (and `patches.csv` and
/// the object tables).
#[test]
fn factors_on_1_2_3_ranks_are_the_single_process_files_byte_for_byte() {
    let dir = temp_dir("factors");
    for scene in ["cube", "cornell"] {
        let one = dir.join(format!("{scene}-single"));
        ok(
            &single(&["factors", scene, "-o", one.to_str().unwrap()]),
            "single process",
        );
        for np in 1..=3 {
            let out = dir.join(format!("{scene}-{np}"));
            let run = mpirun(np, &["factors", scene, "-o", out.to_str().unwrap()], &[]);
            ok(&run, &format!("{scene} on {np} ranks"));
            for f in [
                "F.mtx",
                "stderr.mtx",
                "bound.mtx",
                "patches.csv",
                "objects_F.csv",
                "objects_stderr.csv",
                "objects_bound.csv",
            ] {
                assert!(
                    bytes(&one.join(f)) == bytes(&out.join(f)),
                    "{scene}: {f} on {np} ranks differs from the single process's"
                );
            }
            let stdout = String::from_utf8_lossy(&run.stdout);
            if np > 1 {
                // Rank 0 prints the per-rank table, once.
                assert_eq!(stdout.matches("load imbalance").count(), 1, "{stdout}");
                assert!(stdout.contains(&format!("ranks: {np}")), "{stdout}");
            }
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

fn radiosity_of(dir: &Path) -> Vec<[f32; 3]> {
    radiosity::output::read_exr(&dir.join("radiosity.exr"))
        .expect("radiosity.exr")
        .rgb
}

/// The distributed bake: with `--solver jacobi` the matrix stays distributed and the
/// radiosity is one process's Jacobi radiosity bit for bit (every file); with the default
/// solver (SOR) the matrix is gathered on rank 0 and every file is one process's; and the
/// distributed Jacobi agrees with one process's SOR to the solver tolerance.
#[test]
fn distributed_bake_is_the_single_process_bake() {
    let dir = temp_dir("bake");
    let common = [
        "bake",
        "cornell",
        "--method",
        "flat",
        "--patches",
        "300",
        "--size",
        "64x64",
    ];
    let run_single = |name: &str, extra: &[&str]| {
        let out = dir.join(name);
        let mut args: Vec<&str> = common.to_vec();
        args.extend(extra);
        args.extend(["-o", out.to_str().unwrap()]);
        ok(&single(&args), name);
        out
    };
    let run_mpi = |np: usize, name: &str, extra: &[&str]| {
        let out = dir.join(name);
        let mut args: Vec<&str> = common.to_vec();
        args.extend(extra);
        args.extend(["-o", out.to_str().unwrap()]);
        let run = mpirun(np, &args, &[]);
        ok(&run, name);
        (out, String::from_utf8_lossy(&run.stdout).into_owned())
    };
    let files = ["radiosity.exr", "mesh.ply", "mesh.glb", "preview.png"];
    let jacobi = run_single("jacobi", &["--solver", "jacobi"]);
    for np in [2, 3] {
        let (out, stdout) = run_mpi(np, &format!("jacobi-{np}"), &["--solver", "jacobi"]);
        for f in files {
            assert!(
                bytes(&jacobi.join(f)) == bytes(&out.join(f)),
                "{f}: distributed Jacobi on {np} ranks differs"
            );
        }
        assert!(stdout.contains("solve: jacobi in"), "{stdout}");
    }
    // The default solver (SOR) runs on rank 0 after the gather.
    let gs = run_single("default-solver", &[]);
    let (gathered, _) = run_mpi(2, "default-solver-2", &[]);
    for f in files {
        assert!(
            bytes(&gs.join(f)) == bytes(&gathered.join(f)),
            "{f}: the default solver on rank 0 after the gather differs"
        );
    }
    // Two solutions to a relative residual of 1e-6 (and every patch to 1e-6 of its own
    // value): the radiosities agree far within 1e-4 of the brightest.
    let (a, b) = (radiosity_of(&gs), radiosity_of(&dir.join("jacobi-3")));
    let top = a.iter().flatten().fold(0f32, |m, v| m.max(v.abs()));
    let worst = a
        .iter()
        .flatten()
        .zip(b.iter().flatten())
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, f32::max);
    assert!(worst <= 1e-4 * top, "{worst} of {top}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A rank that fails with an error, or is killed, ends the whole run: a non-zero exit,
/// a message that names the rank, and no output folder (nor a hidden temporary one).
#[test]
fn a_failing_rank_ends_the_run_without_a_folder() {
    let dir = temp_dir("fault");
    for (np, fault, says) in [
        (2, "1:error", "rank 1 of 2: injected failure"),
        (3, "2:error", "rank 2 of 3: injected failure"),
        (2, "1:kill", "rank 1"),
    ] {
        let out = dir.join("out");
        let run = mpirun(
            np,
            &["factors", "cube", "-o", out.to_str().unwrap()],
            &[("RADIOSITY_FAULT", fault)],
        );
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert!(!run.status.success(), "{fault}: {stderr}");
        assert!(stderr.contains(says), "{fault}: {stderr}");
        let left: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert!(left.is_empty(), "{fault}: left {left:?}");
    }
    // Commands that do not share their work are refused on several ranks, as is the
    // hierarchical method.
    let run = mpirun(2, &["bake", "cornell", "--method", "hierarchical"], &[]);
    assert!(!run.status.success());
    assert!(String::from_utf8_lossy(&run.stderr).contains("runs as one process"));
    let run = mpirun(2, &["scenes"], &[]);
    assert!(!run.status.success());
    assert!(String::from_utf8_lossy(&run.stderr).contains("only `factors` and `bake`"));
    let _ = std::fs::remove_dir_all(&dir);
}
