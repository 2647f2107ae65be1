//! Output: per-vertex radiosity and the files made from it.
//!
//! The last stage of the pipeline. It takes the patch radiosity `b` and turns it into
//! something a renderer or a person can use:
//!
//! - [`vertex`]: [`interpolate`] averages patch radiosity onto mesh vertices (area-weighted,
//!   split at creases and material boundaries) into a [`VertexRadiosity`], and any scalar
//!   fields the same way ([`interpolate_fields`]);
//! - [`exr`]: the bake, one pixel per vertex, as a self-describing OpenEXR file
//!   ([`write_exr`], [`read_exr`]);
//! - [`ply`]: the same mesh as a binary PLY with vertex colours, for Blender or MeshLab
//!   ([`write_ply`]);
//! - [`gltf`]: the same mesh as binary glTF 2.0, one node per scene object, in metres
//!   ([`write_glb`]);
//! - [`lightmap`]: the same radiosity as one texture per object in the OBJ's own texture
//!   coordinates, dilated across seams ([`lightmap::write_all`]);
//! - [`preview`]: a small software rasterizer that renders the bake from the scene's camera
//!   into an 8-bit sRGB image ([`render_preview`], [`write_png`]);
//! - [`thermal`]: the thermal mode's per-patch and per-surface tables as CSV, and its
//!   per-vertex `thermal.exr` and `mesh.ply` in the bake's layouts.
//!
//! Every writer goes through [`write_atomic`]: a file is either written whole or not at
//! all, so an interrupted run never leaves a truncated bake that looks valid. A run's files
//! together go through [`write_folder`] ([`folder`]): a folder is whole, from one run, or
//! absent.

pub mod chart;
pub mod exr;
pub mod folder;
pub mod gltf;
pub mod lightmap;
pub mod ply;
pub mod preview;
pub mod thermal;
pub mod vertex;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

pub use self::exr::{
    read_exr, read_vertex_channels, write_exr, write_vertex_channels, ExrBake, VertexChannels,
};
pub use self::folder::{check_folder, write_folder, FolderKind, Manifest};
pub use self::gltf::{write_glb, GlbSettings, Objects};
pub use self::ply::{write_ply, write_ply_with};
pub use self::preview::{render_preview, write_png, Exposure, Image};
pub use self::vertex::{
    interpolate, interpolate_fields, interpolate_with, Nodal, VertexFields, VertexRadiosity,
    DEFAULT_CREASE_DEG,
};

use crate::error::{Error, Result};

/// A CSV field (RFC 4180): quoted when it holds a comma, a quote, or a line break, with
/// quotes doubled; as written, pandas, Python's `csv` and spreadsheets read it back.
pub fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// Writes `value` as pretty-printed JSON with a final newline to `path`, whole or not at
/// all ([`write_atomic`]).
pub fn write_json(path: &Path, value: &impl serde::Serialize) -> Result<()> {
    let json = serde_json::to_string_pretty(value).map_err(|e| Error::Output {
        path: path.to_path_buf(),
        msg: e.to_string(),
    })?;
    write_atomic(path, |t| {
        std::fs::write(t, json + "\n").map_err(|e| Error::io(t, e))
    })
}

/// Writes `path` whole or not at all.
///
/// `f` writes the complete file to a temporary path in the same folder (so that the final
/// rename stays on one file system); the file is then flushed to disk and renamed over
/// `path`, which readers see either in its old state or complete. When `f` fails, the
/// temporary file is removed and `path` is left untouched. Errors that name the temporary
/// file are reported against `path`.
pub fn write_atomic(path: &Path, f: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let name = path.file_name().ok_or_else(|| Error::Output {
        path: path.to_path_buf(),
        msg: "not a file name".into(),
    })?;
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let mut tmp_name = std::ffi::OsString::from(".");
    tmp_name.push(name);
    tmp_name.push(format!(
        ".{}-{}.tmp",
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed)
    ));
    let tmp = dir.join(tmp_name);

    let result = f(&tmp)
        .and_then(|()| {
            std::fs::File::open(&tmp)
                .and_then(|file| file.sync_all())
                .map_err(|e| Error::io(path, e))
        })
        .and_then(|()| std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e)));
    if result.is_err() {
        // Best effort: the temporary file may not exist if `f` failed early.
        let _ = std::fs::remove_file(&tmp);
    }
    result.map_err(|e| rename_path(e, &tmp, path))
}

/// Replaces `tmp` by `path` in an error that names `tmp` or a file inside it.
fn rename_path(e: Error, tmp: &Path, path: &Path) -> Error {
    let swap = |p: PathBuf| match p.strip_prefix(tmp) {
        Ok(rest) if rest.as_os_str().is_empty() => path.to_path_buf(),
        Ok(rest) => path.join(rest),
        Err(_) => p,
    };
    match e {
        Error::Io { path: p, source } => Error::Io {
            path: swap(p),
            source,
        },
        Error::Output { path: p, msg } => Error::Output { path: swap(p), msg },
        Error::Parse { path: p, line, msg } => Error::Parse {
            path: swap(p),
            line,
            msg,
        },
        Error::Mismatch { path: p, msg } => Error::Mismatch { path: swap(p), msg },
        e => e,
    }
}

/// A fresh empty folder under the system temporary folder, for tests.
#[cfg(test)]
pub(crate) fn test_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("radiosity-output-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atomic_write_replaces_whole_file() {
        let dir = test_dir("atomic-ok");
        let path = dir.join("a.txt");
        std::fs::write(&path, "old").unwrap();
        write_atomic(&path, |tmp| {
            assert_ne!(tmp, path.as_path());
            assert_eq!(tmp.parent(), path.parent());
            std::fs::write(tmp, "new").map_err(|e| Error::io(tmp, e))
        })
        .unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "new");
        assert_eq!(
            std::fs::read_dir(&dir).unwrap().count(),
            1,
            "temporary file left behind"
        );
    }

    #[test]
    fn atomic_write_failure_leaves_old_file() {
        let dir = test_dir("atomic-fail");
        let path = dir.join("a.txt");
        std::fs::write(&path, "old").unwrap();
        let err = write_atomic(&path, |tmp| {
            std::fs::write(tmp, "half").map_err(|e| Error::io(tmp, e))?;
            Err(Error::Output {
                path: tmp.to_path_buf(),
                msg: "disk full".into(),
            })
        })
        .unwrap_err();
        // The error names the file the user asked for, not the temporary one.
        assert!(
            matches!(&err, Error::Output { path: p, .. } if *p == path),
            "{err:?}"
        );
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "old");
        assert_eq!(
            std::fs::read_dir(&dir).unwrap().count(),
            1,
            "temporary file left behind"
        );
    }

    #[test]
    fn atomic_write_into_missing_folder_fails_cleanly() {
        let dir = test_dir("atomic-missing");
        let path = dir.join("no/such/folder/a.txt");
        let err = write_atomic(&path, |tmp| {
            std::fs::write(tmp, "x").map_err(|e| Error::io(tmp, e))
        })
        .unwrap_err();
        assert!(
            matches!(&err, Error::Io { path: p, .. } if *p == path),
            "{err:?}"
        );
    }
}
