//! Build script: find Embree 4 and tell the linker where it is.
//!
//! Embree 4 is looked for in this order:
//! 1. `EMBREE_DIR`: a folder holding `libembree4.so` (directly or in `lib/` or `lib64/`);
//! 2. `pkg-config embree4` (Debian 13 and Ubuntu 24.04 ship it as `libembree-dev`);
//! 3. the copy `scripts/provision-embree.sh` unpacks (from the PyPI wheel
//!    `embreex==4.4.0.post1`) into `RADIOSITY_EMBREE_CACHE`, else
//!    `$XDG_CACHE_HOME/radiosity`, else `~/.cache/radiosity` (subfolder `embree-4.4.0`).
//!
//! The build script never downloads anything: `./dev` runs the provisioning script when
//! neither of the first two finds Embree. The folder found is added to the link search
//! path and to the binaries' rpath, so the program runs without `LD_LIBRARY_PATH`. When
//! nothing is found the build stops with one message saying how to provision.

use std::env;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Folder name of the provisioned copy inside the cache (as in `scripts/provision-embree.sh`).
const CACHE_SUBDIR: &str = "embree-4.4.0";

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    for var in [
        "EMBREE_DIR",
        "RADIOSITY_EMBREE_CACHE",
        "XDG_CACHE_HOME",
        "HOME",
        "PKG_CONFIG_PATH",
    ] {
        println!("cargo:rerun-if-env-changed={var}");
    }
    // docs.rs-style builds without linking (e.g. `cargo doc` on a machine without Embree).
    if env::var_os("RADIOSITY_NO_EMBREE_LINK").is_some() {
        return;
    }
    match find_embree() {
        Ok((dir, how)) => {
            println!("cargo:rustc-link-search=native={}", dir.display());
            println!("cargo:rustc-link-arg=-Wl,-rpath,{}", dir.display());
            println!("cargo:rustc-env=RADIOSITY_EMBREE_DIR={}", dir.display());
            println!("cargo:rustc-env=RADIOSITY_EMBREE_FOUND_BY={how}");
        }
        Err(why) => {
            eprintln!(
                "\nerror: Embree 4 (libembree4) was not found ({why}).\n\
                 Provision it with `scripts/provision-embree.sh` (what `./dev` does; needs \
                 python3 with pip and the network once), or set EMBREE_DIR to a folder \
                 holding libembree4.so, or install a system Embree 4 that \
                 `pkg-config embree4` finds (Debian 13 / Ubuntu 24.04 `libembree-dev`).\n"
            );
            std::process::exit(1);
        }
    }
}

/// Finds the folder holding `libembree4.so`, and says which of the three ways found it.
fn find_embree() -> Result<(PathBuf, &'static str), String> {
    if let Some(dir) = env::var_os("EMBREE_DIR") {
        let dir = PathBuf::from(dir);
        return lib_dir_in(&dir)
            .map(|d| (d, "EMBREE_DIR"))
            .ok_or_else(|| format!("EMBREE_DIR={} holds no libembree4.so", dir.display()));
    }
    if let Some(dir) = pkg_config_libdir() {
        return Ok((dir, "pkg-config"));
    }
    provisioned().map(|d| (d, "provisioned"))
}

/// `dir`, `dir/lib` or `dir/lib64`, whichever holds `libembree4.so`.
fn lib_dir_in(dir: &Path) -> Option<PathBuf> {
    [dir.to_path_buf(), dir.join("lib"), dir.join("lib64")]
        .into_iter()
        .find(|d| d.join("libembree4.so").exists())
}

/// The `libdir` of the `embree4` pkg-config package, if it exists and holds the library.
fn pkg_config_libdir() -> Option<PathBuf> {
    let out = Command::new("pkg-config")
        .args(["--variable=libdir", "embree4"])
        .output()
        .ok()?;
    if !out.status.success() {
        return None;
    }
    let dir = PathBuf::from(String::from_utf8_lossy(&out.stdout).trim());
    lib_dir_in(&dir)
}

/// The cache folder for the provisioned copy.
fn cache_dir() -> Result<PathBuf, String> {
    let base = if let Some(d) = env::var_os("RADIOSITY_EMBREE_CACHE") {
        PathBuf::from(d)
    } else if let Some(d) = env::var_os("XDG_CACHE_HOME") {
        PathBuf::from(d).join("radiosity")
    } else if let Some(h) = env::var_os("HOME") {
        PathBuf::from(h).join(".cache").join("radiosity")
    } else {
        return Err("no cache folder: set RADIOSITY_EMBREE_CACHE or HOME".into());
    };
    Ok(base.join(CACHE_SUBDIR))
}

/// The provisioned folder, when `scripts/provision-embree.sh` has filled it.
fn provisioned() -> Result<PathBuf, String> {
    let dir = cache_dir()?;
    println!("cargo:rerun-if-changed={}", dir.join("READY").display());
    if dir.join("READY").exists() && dir.join("libembree4.so").exists() {
        Ok(dir)
    } else {
        Err(format!("{} is not provisioned", dir.display()))
    }
}
