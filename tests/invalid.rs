//! Every file in `scenes/invalid/` must be refused with the message its first line names
//! (`# expect: ...`), by the library and by the command line, without a panic.

use std::path::{Path, PathBuf};
use std::process::Command;

use radiosity::mesh::{PatchSet, Resolution};
use radiosity::scene::Scene;

fn invalid_scenes() -> Vec<(PathBuf, String)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/invalid");
    let mut out = Vec::new();
    for entry in std::fs::read_dir(&dir).expect("scenes/invalid exists") {
        let path = entry.expect("readable folder").path();
        if path.extension().and_then(|e| e.to_str()) != Some("obj") {
            continue;
        }
        // Lossy: some files hold a byte that is not UTF-8 on purpose.
        let text =
            String::from_utf8_lossy(&std::fs::read(&path).expect("readable file")).into_owned();
        let expect = text
            .lines()
            .next()
            .and_then(|l| l.strip_prefix("# expect: "))
            .unwrap_or_else(|| panic!("{} has no `# expect:` first line", path.display()))
            .to_string();
        out.push((path, expect));
    }
    out.sort();
    assert!(
        out.len() >= 10,
        "expected the invalid-input collection, found {}",
        out.len()
    );
    out
}

fn load_all_stages(path: &Path) -> radiosity::Result<()> {
    let scene = Scene::load(path.to_str().expect("utf-8 path"))?;
    scene.require_emitter()?;
    let patches = PatchSet::build(&scene, Resolution::Patches(10))?;
    patches.validate()
}

#[test]
fn library_refuses_each_invalid_scene_with_its_message() {
    for (path, expect) in invalid_scenes() {
        let err = load_all_stages(&path)
            .err()
            .unwrap_or_else(|| panic!("{} was accepted", path.display()))
            .to_string();
        eprintln!("{}: {err}", path.file_name().unwrap().to_string_lossy());
        assert!(
            err.contains(&expect),
            "{}:\n  got:      {err}\n  expected: {expect}",
            path.display()
        );
    }
}

#[test]
fn command_line_reports_errors_without_panicking() {
    let bin = env!("CARGO_BIN_EXE_radiosity");
    let out_dir = std::env::temp_dir().join(format!("radiosity-invalid-{}", std::process::id()));
    let mut cases: Vec<(String, String)> = invalid_scenes()
        .into_iter()
        .map(|(p, e)| (p.display().to_string(), e))
        .collect();
    cases.push((
        "no-such-scene".into(),
        "no built-in scene `no-such-scene`".into(),
    ));
    cases.push((
        "/nonexistent/box.obj".into(),
        "/nonexistent/box.obj: No such file".into(),
    ));
    for (scene, expect) in cases {
        let out = Command::new(bin)
            .args(["bake", &scene, "--patches", "10", "-o"])
            .arg(&out_dir)
            .output()
            .expect("binary runs");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{scene}: exit status was success");
        assert_eq!(out.status.code(), Some(1), "{scene}: {stderr}");
        assert!(!stderr.contains("panicked"), "{scene}: {stderr}");
        assert!(
            stderr.contains(&expect),
            "{scene}:\n  got:      {stderr}\n  expected: {expect}"
        );
    }
    assert!(
        !out_dir.join("radiosity.exr").exists(),
        "no output may be written for bad input"
    );
}
