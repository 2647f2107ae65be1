//! Output folders written whole or not at all: [`write_folder`].
//!
//! A bake (`radiosity.exr`, `mesh.ply`, `preview.png`...) or a factors folder (`F.mtx` and
//! `stderr.mtx` or their npz pair, `patches.csv`, `provenance.json`) is only meaningful as a set: files from
//! two runs side by side are a silent wrong answer. So every file of a run is written into a
//! temporary sibling folder, a `manifest.json` naming the run and every file (size and
//! SHA-256; a file its writer hashed already is not read again: [`write_folder_hashed`])
//! is added, and the folder is renamed into place:
//!
//! - no folder at the path, or an empty one: the new folder is renamed there;
//! - a folder this tool wrote before for the same [`FolderKind`] (it has a `manifest.json`
//!   of that kind, or, for folders older than the manifest, it holds only file names such a
//!   run writes): it is renamed aside, the new one renamed in, the old one removed;
//! - anything else (a file, a folder holding other files, a folder of the other kind) is
//!   refused before any work is done ([`check_folder`]) and again before the rename, and
//!   left untouched.
//!
//! A run killed at any point leaves at the path either the old folder, the new one or
//! nothing (between the two renames), never a mix. Temporaries are hidden siblings named
//! `.NAME.radiosity-tmp.PID.K` (being written) and `.NAME.radiosity-old.PID.K` (a
//! replaced folder being removed); the next run into the same path removes those whose
//! process is gone. Concurrent runs into one path each end with a whole folder there (the
//! last rename wins).

use std::ffi::OsString;
use std::io::Read as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use super::rename_path;
use crate::error::{Error, Result};

/// The manifest's file name, in every folder [`write_folder`] writes.
pub const MANIFEST: &str = "manifest.json";

/// Which run wrote a folder: what [`write_folder`] may replace.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FolderKind {
    /// A bake: `radiosity.exr`, `mesh.ply`, previews.
    Bake,
    /// A factors folder: `F.mtx` and `stderr.mtx` (or `F.npz` and `stderr.npz`),
    /// `patches.csv`, the object tables, `provenance.json`.
    Factors,
    /// A thermal solution: `patches.csv`, `surfaces.csv`, `thermal.exr`, `mesh.ply`.
    Thermal,
}

impl FolderKind {
    /// Whether a folder without a manifest (written before manifests existed) may hold a
    /// file of this name.
    fn legacy_name(self, name: &str) -> bool {
        // Temporary files of `write_atomic` (`.NAME.PID-K.tmp`).
        if name.starts_with('.') && name.ends_with(".tmp") {
            return true;
        }
        match self {
            FolderKind::Bake => {
                matches!(name, "radiosity.exr" | "mesh.ply" | "preview.png")
                    || (name.starts_with("preview-step-") && name.ends_with(".png"))
            }
            FolderKind::Factors => matches!(
                name,
                "F.mtx" | "stderr.mtx" | "patches.csv" | "provenance.json"
            ),
            // Written with a manifest from the start.
            FolderKind::Thermal => false,
        }
    }
}

/// One file of a [`Manifest`].
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ManifestFile {
    /// File name inside the folder.
    pub name: String,
    /// Size in bytes.
    pub bytes: u64,
    /// SHA-256 of the content, lower-case hex.
    pub sha256: String,
}

impl ManifestFile {
    /// The record of `dir/name` as it is on disk: its size and SHA-256, read from the file.
    pub fn of(dir: &Path, name: &str) -> Result<ManifestFile> {
        let (bytes, sha256) = sha256_file(&dir.join(name))?;
        Ok(ManifestFile {
            name: name.to_string(),
            bytes,
            sha256,
        })
    }
}

/// `manifest.json`: the run that wrote a folder and every file it wrote.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Manifest {
    /// Crate name and version.
    pub writer: String,
    /// What the folder holds.
    pub kind: FolderKind,
    /// An identifier of the run, different for every run.
    pub run: String,
    /// The files besides the manifest, sorted by name.
    pub files: Vec<ManifestFile>,
}

impl Manifest {
    /// Reads `dir/manifest.json`.
    pub fn read(dir: &Path) -> Result<Manifest> {
        let path = dir.join(MANIFEST);
        let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
        serde_json::from_str(&text).map_err(|e| Error::Parse {
            path,
            line: Some(e.line()),
            msg: e.to_string(),
        })
    }

    /// Checks that `dir` holds exactly the files of the manifest, with their sizes and
    /// hashes: the folder is whole and from one run.
    pub fn verify(&self, dir: &Path) -> Result<()> {
        let mut names = list(dir)?;
        names.retain(|n| n != MANIFEST);
        let listed: Vec<&str> = self.files.iter().map(|f| f.name.as_str()).collect();
        if let Some(extra) = names.iter().find(|n| !listed.contains(&n.as_str())) {
            return Err(Error::Mismatch {
                path: dir.join(extra),
                msg: format!("not in {MANIFEST} of run {}", self.run),
            });
        }
        for f in &self.files {
            let path = dir.join(&f.name);
            let (bytes, sha256) = sha256_file(&path)?;
            if bytes != f.bytes || sha256 != f.sha256 {
                return Err(Error::Mismatch {
                    path,
                    msg: format!(
                        "{bytes} bytes with SHA-256 {sha256}; {MANIFEST} of run {} says {} \
                         bytes with {}",
                        self.run, f.bytes, f.sha256
                    ),
                });
            }
        }
        Ok(())
    }
}

/// Size and lower-case hex SHA-256 of a file.
pub fn sha256_file(path: &Path) -> Result<(u64, String)> {
    let mut file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 1 << 16];
    let mut bytes = 0u64;
    loop {
        let k = file.read(&mut buf).map_err(|e| Error::io(path, e))?;
        if k == 0 {
            break;
        }
        hasher.update(&buf[..k]);
        bytes += k as u64;
    }
    Ok((bytes, hex(&hasher.finalize())))
}

/// Lower-case hex of `bytes`.
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Sorted names of the entries of `dir`.
fn list(dir: &Path) -> Result<Vec<String>> {
    let mut names = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))? {
        let entry = entry.map_err(|e| Error::io(dir, e))?;
        names.push(entry.file_name().to_string_lossy().into_owned());
    }
    names.sort();
    Ok(names)
}

/// Refuses `dir` unless [`write_folder`] may put a folder of `kind` there: it does not
/// exist, or is an empty folder, or a folder a previous run of `kind` wrote. Call it before
/// the expensive work, so a run is refused at once rather than at the end.
pub fn check_folder(dir: &Path, kind: FolderKind) -> Result<()> {
    let meta = match std::fs::symlink_metadata(dir) {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(Error::io(dir, e)),
    };
    let refuse = |msg: String| Error::Output {
        path: dir.to_path_buf(),
        msg,
    };
    if !meta.is_dir() {
        return Err(refuse(
            "exists and is not a folder (the output is a folder of files; name a new or \
             empty folder)"
                .into(),
        ));
    }
    let names = list(dir)?;
    if names.iter().any(|n| n == MANIFEST) {
        let m = Manifest::read(dir)?;
        if m.kind != kind {
            return Err(refuse(format!(
                "holds a {} folder (see its {MANIFEST}); it is not replaced by a {} \
                 (name another folder)",
                kind_name(m.kind),
                kind_name(kind)
            )));
        }
        return Ok(());
    }
    if let Some(other) = names.iter().find(|n| !kind.legacy_name(n)) {
        return Err(refuse(format!(
            "holds `{other}`, which a radiosity {} does not write; a non-empty folder is only \
             replaced when a previous {} wrote it (name a new or empty folder)",
            kind_name(kind),
            kind_name(kind)
        )));
    }
    Ok(())
}

fn kind_name(kind: FolderKind) -> &'static str {
    match kind {
        FolderKind::Bake => "bake",
        FolderKind::Factors => "factors run",
        FolderKind::Thermal => "thermal run",
    }
}

/// The hidden sibling `.NAME.radiosity-WHAT.PID.K` of `dir`.
fn sibling(parent: &Path, name: &std::ffi::OsStr, what: &str, n: u64) -> PathBuf {
    let mut s = OsString::from(".");
    s.push(name);
    s.push(format!(".radiosity-{what}.{}.{n}", std::process::id()));
    parent.join(s)
}

/// Removes the temporaries of `dir` left by runs whose process is gone.
fn clean_stale(parent: &Path, name: &std::ffi::OsStr) {
    let Ok(entries) = std::fs::read_dir(parent) else {
        return;
    };
    // Without /proc the owner cannot be told alive or gone: leave everything.
    if !Path::new("/proc/self").exists() {
        return;
    }
    let prefix = format!(".{}.radiosity-", name.to_string_lossy());
    for entry in entries.flatten() {
        let file_name = entry.file_name().to_string_lossy().into_owned();
        let Some(rest) = file_name.strip_prefix(&prefix) else {
            continue;
        };
        // `tmp.PID.K` or `old.PID.K`.
        let mut parts = rest.split('.');
        let (Some("tmp" | "old"), Some(pid), Some(_), None) =
            (parts.next(), parts.next(), parts.next(), parts.next())
        else {
            continue;
        };
        let Ok(pid) = pid.parse::<u32>() else {
            continue;
        };
        if pid != std::process::id() && !Path::new(&format!("/proc/{pid}")).exists() {
            let _ = std::fs::remove_dir_all(entry.path());
        }
    }
}

/// A run identifier: time, process and a counter, hashed.
fn run_id(n: u64) -> String {
    let t = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    let h = Sha256::digest(format!("{t} {} {n}", std::process::id()));
    hex(&h[..8])
}

/// Writes a whole folder at `dir`, or nothing (see the [module docs](self)).
///
/// `f` gets an empty temporary folder beside `dir` and writes every file of the run into
/// it (flat, no sub-folders); its value is returned. Then `manifest.json` is added and the
/// folder renamed to `dir`, replacing a folder a previous run of the same `kind` wrote.
/// When `f` fails, the temporary folder is removed and `dir` is untouched; errors that
/// name a file in the temporary folder are reported against `dir`. `dir`'s parent folders
/// are created when missing.
///
/// ```no_run
/// use radiosity::output::{write_folder, FolderKind};
/// # fn main() -> radiosity::Result<()> {
/// write_folder("out".as_ref(), FolderKind::Bake, |tmp| {
///     std::fs::write(tmp.join("notes.txt"), "...").map_err(|e| radiosity::Error::io(tmp, e))
/// })?;
/// # Ok(())
/// # }
/// ```
pub fn write_folder<T>(
    dir: &Path,
    kind: FolderKind,
    f: impl FnOnce(&Path) -> Result<T>,
) -> Result<T> {
    write_folder_hashed(dir, kind, |tmp| Ok((f(tmp)?, Vec::new())))
}

/// [`write_folder`] for a writer that hashes files itself (a factors folder records their
/// SHA-256 in its provenance): besides its value, `f` returns the [`ManifestFile`]s of the
/// files it hashed ([`ManifestFile::of`], once each file is complete), and the manifest
/// takes them as they are, so each file is read and hashed once. The files `f` has no
/// record for (and any whose size no longer matches its record) are hashed for the
/// manifest; a record of a file that is not in the folder is an error.
pub fn write_folder_hashed<T>(
    dir: &Path,
    kind: FolderKind,
    f: impl FnOnce(&Path) -> Result<(T, Vec<ManifestFile>)>,
) -> Result<T> {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    check_folder(dir, kind)?;
    let name = dir.file_name().ok_or_else(|| Error::Output {
        path: dir.to_path_buf(),
        msg: "not a folder name".into(),
    })?;
    let parent = match dir.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).map_err(|e| Error::io(&parent, e))?;
    clean_stale(&parent, name);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    let tmp = sibling(&parent, name, "tmp", n);
    std::fs::create_dir(&tmp).map_err(|e| Error::io(dir, e))?;
    let result = f(&tmp)
        .and_then(|(value, hashed)| {
            write_manifest(&tmp, kind, &run_id(n), hashed)?;
            Ok(value)
        })
        .and_then(|value| {
            swap_in(&tmp, dir, &parent, name, kind, n)?;
            Ok(value)
        });
    if result.is_err() {
        let _ = std::fs::remove_dir_all(&tmp);
    }
    result.map_err(|e| rename_path(e, &tmp, dir))
}

/// Adds `manifest.json` to `tmp` and flushes the folder to disk. `hashed` are records of
/// files of `tmp` the writer already hashed (see [`write_folder_hashed`]): only the other
/// files are hashed here.
fn write_manifest(
    tmp: &Path,
    kind: FolderKind,
    run: &str,
    hashed: Vec<ManifestFile>,
) -> Result<()> {
    // Hashed side by side: a folder may hold several files of hundreds of MB, and hashing
    // is one core's work per file.
    use rayon::prelude::*;
    let mut known: std::collections::BTreeMap<String, ManifestFile> =
        hashed.into_iter().map(|f| (f.name.clone(), f)).collect();
    let names: Vec<(String, Option<ManifestFile>)> = list(tmp)?
        .into_iter()
        .map(|name| {
            let record = known.remove(&name);
            (name, record)
        })
        .collect();
    if let Some(name) = known.keys().next() {
        return Err(Error::Output {
            path: tmp.join(name),
            msg: "hashed by its writer but not in the folder".into(),
        });
    }
    let files = names
        .into_par_iter()
        .map(|(name, record)| {
            let path = tmp.join(&name);
            let meta = std::fs::symlink_metadata(&path).map_err(|e| Error::io(&path, e))?;
            if !meta.is_file() {
                return Err(Error::Output {
                    path,
                    msg: "an output folder holds regular files only".into(),
                });
            }
            match record {
                Some(f) if f.bytes == meta.len() => Ok(f),
                _ => ManifestFile::of(tmp, &name),
            }
        })
        .collect::<Result<Vec<_>>>()?;
    let manifest = Manifest {
        writer: format!("radiosity {}", env!("CARGO_PKG_VERSION")),
        kind,
        run: run.to_string(),
        files,
    };
    let path = tmp.join(MANIFEST);
    super::write_json(&path, &manifest)?;
    sync_dir(tmp);
    Ok(())
}

/// Flushes a folder's entries to disk (best effort: not every file system can).
fn sync_dir(dir: &Path) {
    if let Ok(d) = std::fs::File::open(dir) {
        let _ = d.sync_all();
    }
}

/// Renames `tmp` to `dir`, moving a previous folder there aside first and removing it after.
fn swap_in(
    tmp: &Path,
    dir: &Path,
    parent: &Path,
    name: &std::ffi::OsStr,
    kind: FolderKind,
    n: u64,
) -> Result<()> {
    let old = sibling(parent, name, "old", n);
    let mut moved_aside = false;
    // Concurrent runs may put a folder back between our two renames: try a few times.
    for _ in 0..16 {
        match std::fs::rename(tmp, dir) {
            Ok(()) => {
                sync_dir(parent);
                if moved_aside {
                    let _ = std::fs::remove_dir_all(&old);
                }
                return Ok(());
            }
            Err(e) if std::fs::symlink_metadata(dir).is_err() => return Err(Error::io(dir, e)),
            Err(_) => {}
        }
        // Something is at `dir`: replace it only if `check_folder` still allows it (a
        // folder another run moves away meanwhile is no reason to fail: try again).
        if let Err(e) = check_folder(dir, kind) {
            if std::fs::symlink_metadata(dir).is_ok() {
                return Err(e);
            }
            continue;
        }
        if moved_aside {
            let _ = std::fs::remove_dir_all(&old);
        }
        match std::fs::rename(dir, &old) {
            Ok(()) => moved_aside = true,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(Error::io(dir, e)),
        }
    }
    Err(Error::Output {
        path: dir.to_path_buf(),
        msg: "other runs keep writing this folder; try again".into(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::test_dir;

    fn write(dir: &Path, files: &[(&str, &str)]) -> Result<()> {
        write_folder(dir, FolderKind::Bake, |tmp| {
            for (name, text) in files {
                std::fs::write(tmp.join(name), text).map_err(|e| Error::io(tmp.join(name), e))?;
            }
            Ok(())
        })
    }

    #[test]
    fn a_folder_is_replaced_as_a_whole() {
        let root = test_dir("folder-whole");
        let dir = root.join("out");
        write(
            &dir,
            &[("radiosity.exr", "one"), ("preview-step-0001.png", "x")],
        )
        .unwrap();
        let first = Manifest::read(&dir).unwrap();
        first.verify(&dir).unwrap();
        write(&dir, &[("radiosity.exr", "two"), ("mesh.ply", "two")]).unwrap();
        let second = Manifest::read(&dir).unwrap();
        second.verify(&dir).unwrap();
        assert_ne!(first.run, second.run);
        assert!(
            !dir.join("preview-step-0001.png").exists(),
            "a file of the old run stayed"
        );
        assert_eq!(
            std::fs::read_to_string(dir.join("mesh.ply")).unwrap(),
            "two"
        );
        // Nothing but the folder is left in the parent.
        assert_eq!(list(&root).unwrap(), ["out"]);
    }

    #[test]
    fn a_failed_run_leaves_the_old_folder() {
        let root = test_dir("folder-fail");
        let dir = root.join("out");
        write(&dir, &[("radiosity.exr", "one")]).unwrap();
        let err = write_folder(&dir, FolderKind::Bake, |tmp| -> Result<()> {
            std::fs::write(tmp.join("radiosity.exr"), "half").unwrap();
            Err(Error::Output {
                path: tmp.join("radiosity.exr"),
                msg: "disk full".into(),
            })
        })
        .unwrap_err();
        // Reported against the folder asked for, not the temporary one.
        assert!(
            matches!(&err, Error::Output { path, .. } if *path == dir.join("radiosity.exr")),
            "{err:?}"
        );
        assert_eq!(
            std::fs::read_to_string(dir.join("radiosity.exr")).unwrap(),
            "one"
        );
        assert_eq!(list(&root).unwrap(), ["out"]);
    }

    #[test]
    fn foreign_folders_and_files_are_refused() {
        let root = test_dir("folder-refuse");
        let file = root.join("a-file");
        std::fs::write(&file, "mine").unwrap();
        let err = write(&file, &[("radiosity.exr", "x")])
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("a-file") && err.contains("not a folder"),
            "{err}"
        );
        let mine = root.join("mine");
        std::fs::create_dir(&mine).unwrap();
        std::fs::write(mine.join("thesis.tex"), "mine").unwrap();
        let err = write(&mine, &[("radiosity.exr", "x")])
            .unwrap_err()
            .to_string();
        assert!(err.contains("thesis.tex"), "{err}");
        assert_eq!(
            std::fs::read_to_string(mine.join("thesis.tex")).unwrap(),
            "mine"
        );
        // A factors folder is not replaced by a bake.
        let factors = root.join("factors");
        write_folder(&factors, FolderKind::Factors, |_| Ok(())).unwrap();
        let err = write(&factors, &[("radiosity.exr", "x")])
            .unwrap_err()
            .to_string();
        assert!(err.contains("factors"), "{err}");
        // An empty folder and a folder of an older version's bake are replaced.
        let empty = root.join("empty");
        std::fs::create_dir(&empty).unwrap();
        write(&empty, &[("radiosity.exr", "x")]).unwrap();
        let legacy = root.join("legacy");
        std::fs::create_dir(&legacy).unwrap();
        std::fs::write(legacy.join("preview.png"), "old").unwrap();
        write(&legacy, &[("radiosity.exr", "x")]).unwrap();
        assert!(!legacy.join("preview.png").exists());
    }

    #[test]
    fn stale_temporaries_of_dead_runs_are_removed() {
        let root = test_dir("folder-stale");
        // A process id that cannot be running (above the kernel's pid_max limit).
        let dead = root.join(".out.radiosity-tmp.4294967295.0");
        std::fs::create_dir(&dead).unwrap();
        std::fs::write(dead.join("radiosity.exr"), "half").unwrap();
        let aside = root.join(".out.radiosity-old.4294967295.3");
        std::fs::create_dir(&aside).unwrap();
        // One of a live process (this one) is left alone.
        let live = sibling(&root, "out".as_ref(), "tmp", 99);
        std::fs::create_dir(&live).unwrap();
        write(&root.join("out"), &[("radiosity.exr", "x")]).unwrap();
        assert!(!dead.exists() && !aside.exists());
        assert!(live.exists());
        let _ = std::fs::remove_dir_all(&live);
    }

    #[test]
    fn the_manifest_takes_the_writers_hashes() {
        let root = test_dir("folder-hashed");
        let dir = root.join("out");
        // A record the manifest takes as it is (its hash is not the file's: the file is
        // not read again), a stale one (the file grew since) and none.
        let taken = ManifestFile {
            name: "radiosity.exr".into(),
            bytes: 3,
            sha256: "recorded".into(),
        };
        write_folder_hashed(&dir, FolderKind::Bake, |tmp| {
            for name in ["radiosity.exr", "mesh.ply", "preview.png"] {
                std::fs::write(tmp.join(name), "one").unwrap();
            }
            let stale = ManifestFile::of(tmp, "mesh.ply")?;
            std::fs::write(tmp.join("mesh.ply"), "two!").unwrap();
            Ok(((), vec![taken.clone(), stale]))
        })
        .unwrap();
        let m = Manifest::read(&dir).unwrap();
        let names: Vec<&str> = m.files.iter().map(|f| f.name.as_str()).collect();
        assert_eq!(names, ["mesh.ply", "preview.png", "radiosity.exr"]);
        assert_eq!(m.files[0], ManifestFile::of(&dir, "mesh.ply").unwrap());
        assert_eq!(m.files[1], ManifestFile::of(&dir, "preview.png").unwrap());
        assert_eq!(m.files[2], taken);
        // A record of a file the folder does not hold fails the run.
        let absent = ManifestFile {
            name: "mesh.glb".into(),
            ..taken
        };
        let err = write_folder_hashed(&dir, FolderKind::Bake, |tmp| {
            std::fs::write(tmp.join("radiosity.exr"), "two").unwrap();
            Ok(((), vec![absent]))
        })
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("mesh.glb") && err.contains("not in the folder"),
            "{err}"
        );
        // The folder of the first run is left.
        assert_eq!(Manifest::read(&dir).unwrap(), m);
    }

    #[test]
    fn the_manifest_finds_a_mixed_folder() {
        let root = test_dir("folder-mixed");
        let dir = root.join("out");
        write(&dir, &[("radiosity.exr", "one"), ("mesh.ply", "one")]).unwrap();
        std::fs::write(dir.join("mesh.ply"), "two").unwrap();
        let err = Manifest::read(&dir)
            .unwrap()
            .verify(&dir)
            .unwrap_err()
            .to_string();
        assert!(err.contains("mesh.ply"), "{err}");
    }
}
