//! The command line as a careless user or an attacker drives it: a file where a folder is
//! expected, special files as inputs, runs too large for the machine, absurd counts. Each
//! is refused with exit status 1 and a message saying what is wrong, without a panic and
//! before any work.

use std::path::PathBuf;
use std::process::{Command, Output};

fn temp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("radiosity-rel-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp folder");
    d
}

fn radiosity(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_radiosity"))
        .args(args)
        .output()
        .expect("binary runs")
}

/// Runs and expects a refusal whose message holds every one of `want`.
fn refused(args: &[&str], want: &[&str]) {
    let out = radiosity(args);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{args:?}: {stderr}");
    assert!(!stderr.contains("panicked"), "{args:?}: {stderr}");
    for w in want {
        assert!(
            stderr.contains(w),
            "{args:?}:\n  got:      {stderr}\n  expected: {w}"
        );
    }
}

#[test]
fn an_output_that_is_a_file_or_a_foreign_folder_is_refused() {
    let dir = temp_dir("out");
    let file = dir.join("notes.txt");
    std::fs::write(&file, "mine").expect("write");
    let f = file.to_str().unwrap();
    refused(
        &["bake", "--patches", "20", "-o", f],
        &["notes.txt", "is not a folder"],
    );
    refused(
        &["factors", "cornell", "--patches", "20", "-o", f],
        &["is not a folder"],
    );
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "mine");
    let d = dir.to_str().unwrap();
    refused(
        &["bake", "--patches", "20", "-o", d],
        &["holds `notes.txt`"],
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn special_files_as_inputs_are_refused_without_blocking() {
    refused(
        &["bake", "/dev/zero", "--patches", "20"],
        &["/dev/zero", "not a regular file"],
    );
    let dir = temp_dir("fifo");
    let obj = dir.join("scene.obj");
    std::fs::write(
        &obj,
        "mtllib pipe.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    )
    .unwrap();
    let made = Command::new("mkfifo").arg(dir.join("pipe.mtl")).status();
    if made.is_ok_and(|s| s.success()) {
        refused(
            &["bake", obj.to_str().unwrap(), "--patches", "20"],
            &["scene.obj:1", "pipe.mtl", "not a regular file"],
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn runs_too_large_are_refused_before_any_work() {
    let dir = temp_dir("large");
    let o = dir.join("out");
    let o = o.to_str().unwrap();
    refused(
        &["bake", "--patches", "50000000", "-o", o],
        &["50000000 patches", "--patches", "--max-memory"],
    );
    refused(
        &[
            "bake",
            "--method",
            "flat",
            "--patches",
            "2000",
            "--max-memory",
            "64M",
            "-o",
            o,
        ],
        &["more than the 0.06 GiB --max-memory", "--patches"],
    );
    refused(
        &["bake", "--max-edge", "1e-9", "-o", o],
        &["patches, more than the 100000000 a run accepts"],
    );
    refused(
        &["bake", "--patches", "5000", "--solver", "direct", "-o", o],
        &["limited to 4096 patches", "--solver cg"],
    );
    assert!(!std::path::Path::new(o).exists());
    refused(
        &["bake", "--size", "8192x8192", "--max-memory", "1G", "-o", o],
        &["--size"],
    );
    refused(
        &["bake", "--patches", "18446744073709551615"],
        &["--patches must be at most"],
    );
    refused(
        &["bake", "--replicates", "100000"],
        &["--replicates must be between 2"],
    );
    // A malformed size is a usage error (clap's exit status 2).
    let out = radiosity(&["bake", "--max-memory", "lots"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains("--max-memory") && stderr.contains("4G"),
        "{stderr}"
    );
    assert!(!PathBuf::from(o).exists(), "nothing may be written");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Runs the binary with writes capped at `kib` KiB per file (`RLIMIT_FSIZE`, with
/// `SIGXFSZ` ignored so that a write past the cap fails with `EFBIG`, as a full disk fails
/// one with `ENOSPC`).
fn radiosity_capped(kib: u64, args: &[&str]) -> Output {
    Command::new("bash")
        .arg("-c")
        .arg(format!("trap '' XFSZ; ulimit -f {kib}; exec \"$0\" \"$@\""))
        .arg(env!("CARGO_BIN_EXE_radiosity"))
        .args(args)
        .output()
        .expect("bash runs")
}

#[test]
fn a_write_that_fails_midway_leaves_the_previous_folder_whole() {
    let dir = temp_dir("fsize");
    for (kind, args) in [
        (
            "bake",
            vec![
                "bake",
                "cornell",
                "--method",
                "flat",
                "--patches",
                "100",
                "--size",
                "64x64",
            ],
        ),
        ("factors", vec!["factors", "cornell", "--patches", "100"]),
    ] {
        let out_dir = dir.join(kind);
        let out_s = out_dir.to_str().expect("utf-8 path");
        let full: Vec<&str> = args.iter().copied().chain(["-o", out_s]).collect();
        let first = radiosity(&full);
        assert!(
            first.status.success(),
            "{}",
            String::from_utf8_lossy(&first.stderr)
        );
        let manifest = std::fs::read(out_dir.join("manifest.json")).expect("manifest");
        let files: Vec<_> = std::fs::read_dir(&out_dir)
            .expect("folder")
            .map(|e| e.expect("entry").file_name())
            .collect();
        // Every output is over 4 KiB: the first write past the cap fails.
        let second = radiosity_capped(4, &full);
        let stderr = String::from_utf8_lossy(&second.stderr);
        assert_eq!(second.status.code(), Some(1), "{kind}: {stderr}");
        assert!(!stderr.contains("panicked"), "{kind}: {stderr}");
        assert!(stderr.contains("File too large"), "{kind}: {stderr}");
        assert_eq!(
            std::fs::read(out_dir.join("manifest.json")).expect("manifest"),
            manifest,
            "{kind}: the previous folder must be untouched"
        );
        let after: Vec<_> = std::fs::read_dir(&out_dir)
            .expect("folder")
            .map(|e| e.expect("entry").file_name())
            .collect();
        assert_eq!(after, files, "{kind}");
        let left: Vec<_> = std::fs::read_dir(&dir)
            .expect("parent")
            .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
            .filter(|n| n.contains("radiosity-tmp") || n.contains("radiosity-old"))
            .collect();
        assert!(left.is_empty(), "{kind}: temporaries left: {left:?}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn flags_that_do_nothing_are_refused_before_any_work() {
    let dir = temp_dir("meaningless");
    let out = dir.join("out");
    let out = out.to_str().expect("utf-8");
    // The folder does not even exist: the refusal comes before it is read.
    for flag in [
        &["--estimator", "hemisphere"][..],
        &["--samples", "5"],
        &["--tol", "1e-3"],
        &["--seed", "7"],
    ] {
        let mut args = vec!["bake", "cornell", "--factors", "/nonexistent", "-o", out];
        args.extend_from_slice(flag);
        refused(
            &args,
            &[&format!("{} has no effect with --factors", flag[0])],
        );
    }
    refused(
        &[
            "bake",
            "cornell",
            "--method",
            "hierarchical",
            "--replicates",
            "8",
            "-o",
            out,
        ],
        &["--replicates sets the flat form-factor estimator"],
    );
    refused(
        &["bake", "cornell", "--exposure", "-1", "-o", out],
        &["--exposure `-1`: expected `auto` or a positive number"],
    );
    assert!(!dir.join("out").exists());
    // An I/O cause is printed once, in the message that names the file.
    let o = radiosity(&["bake", "/nonexistent/scene.obj", "-o", out]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{stderr}");
    assert_eq!(
        stderr.matches("No such file or directory").count(),
        1,
        "{stderr}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn summaries_fit_80_columns_and_a_reused_matrix_reports_no_ray_rate() {
    let dir = temp_dir("columns");
    let factors = dir.join("factors");
    let f = factors.to_str().expect("utf-8");
    let made = radiosity(&["factors", "cornell", "--patches", "150", "-o", f]);
    assert!(
        made.status.success(),
        "{}",
        String::from_utf8_lossy(&made.stderr)
    );
    let out = dir.join("bake");
    let bake = radiosity(&[
        "bake",
        "cornell",
        "--patches",
        "150",
        "--size",
        "32x32",
        "--factors",
        f,
        "-o",
        out.to_str().expect("utf-8"),
    ]);
    assert!(
        bake.status.success(),
        "{}",
        String::from_utf8_lossy(&bake.stderr)
    );
    let hier = radiosity(&[
        "bake",
        "cornell",
        "--method",
        "hierarchical",
        "--error",
        "0.05",
        "--size",
        "32x32",
        "-o",
        dir.join("hier").to_str().expect("utf-8"),
    ]);
    assert!(
        hier.status.success(),
        "{}",
        String::from_utf8_lossy(&hier.stderr)
    );
    for o in [&made, &bake, &hier] {
        for line in String::from_utf8_lossy(&o.stdout).lines() {
            // Only a single word (a path) may be longer.
            assert!(
                line.chars().count() <= 80 || !line.trim().contains(' '),
                "{} columns: {line}",
                line.chars().count()
            );
        }
    }
    let text = String::from_utf8_lossy(&bake.stdout);
    assert!(
        !text.contains("Mrays/s") && text.contains("read from the stored"),
        "{text}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_preview_camera_is_set_on_the_command_line_and_checked() {
    let dir = temp_dir("camera");
    let bake = |tag: &str, camera: Option<&str>| -> Vec<u8> {
        let out = dir.join(tag);
        let mut args = vec![
            "bake",
            "cornell",
            "--method",
            "flat",
            "--patches",
            "100",
            "--size",
            "48x48",
            "-o",
        ];
        let o = out.to_str().expect("utf-8").to_string();
        args.push(&o);
        if let Some(c) = camera {
            args.extend(["--camera", c]);
        }
        let r = radiosity(&args);
        assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
        std::fs::read(out.join("preview.png")).expect("preview")
    };
    // The scene's own `#@camera`, given on the command line: the same picture.
    let own = bake("own", None);
    assert_eq!(own, bake("same", Some("278,273,-800,278,273,0,0,1,0,39.3")));
    // Another camera (negative coordinates first): another picture.
    assert_ne!(own, bake("other", Some("-100,273,-500,278,200,0,0,1,0,60")));
    let out = dir.join("bad");
    let out = out.to_str().expect("utf-8");
    for (camera, want) in [
        ("1,2,3,1,2,3", "the eye and the target are the same point"),
        ("0,0,0,0,1,0", "along the line of sight"),
        ("0,0,0,1,0,0,0,1,0,200", "between 1 and 179 degrees"),
        ("1,2", "got 2 numbers"),
        ("a,b,c,d,e,f", "expected EX,EY,EZ"),
    ] {
        refused(&["bake", "cornell", "--camera", camera, "-o", out], &[want]);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// The dense solve's limit is known from the patch count: a bake over it is refused after
/// meshing, before any form factor (it was refused only after them: 2 to 3 minutes of
/// rays lost on the Cornell box at 5000 patches), and writes nothing.
#[test]
fn a_direct_solve_over_its_limit_is_refused_before_any_form_factor() {
    use radiosity::mesh::Resolution;
    use radiosity::pipeline::{self, BakeConfig, Observer};
    use radiosity::solve::Method;
    use std::sync::Mutex;

    #[derive(Default)]
    struct Stages(Mutex<Vec<String>>);
    impl Observer for Stages {
        fn begin(&self, stage: &str, _total: u64) {
            self.0.lock().unwrap().push(stage.to_string());
        }
    }
    let dir = temp_dir("direct");
    let cfg = BakeConfig {
        out_dir: dir.join("out"),
        resolution: Resolution::Patches(5000),
        method: Method::Direct,
        ..BakeConfig::default()
    };
    let log = Stages::default();
    let e = pipeline::bake(&cfg, &log).unwrap_err().to_string();
    assert!(e.contains("limited to 4096 patches"), "{e}");
    let stages = log.0.into_inner().unwrap();
    assert!(stages.iter().any(|s| s == "mesh"), "{stages:?}");
    assert!(!stages.iter().any(|s| s == "form factors"), "{stages:?}");
    assert!(!dir.join("out").exists());
}

/// Every command's `--help` is plain text: no rustdoc link (`` [`Name`] ``) from a doc
/// comment leaks into what a user reads.
#[test]
fn help_has_no_rustdoc_links() {
    let top = radiosity(&["--help"]);
    assert!(top.status.success());
    let text = String::from_utf8_lossy(&top.stdout).to_string();
    let commands: Vec<String> = text
        .lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| l.starts_with("  "))
        .filter_map(|l| l.split_whitespace().next().map(str::to_string))
        .filter(|c| c != "help")
        .collect();
    assert!(commands.len() >= 5, "{commands:?}");
    for c in [None].into_iter().chain(commands.iter().map(Some)) {
        let args: Vec<&str> = c
            .map(String::as_str)
            .into_iter()
            .chain(["--help"])
            .collect();
        let out = radiosity(&args);
        assert!(out.status.success(), "{args:?}");
        let help = String::from_utf8_lossy(&out.stdout);
        for (k, line) in help.lines().enumerate() {
            assert!(
                !line.contains("[`") && !line.contains("`]"),
                "{args:?} line {}: {line}",
                k + 1
            );
        }
    }
}
