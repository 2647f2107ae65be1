//! Build script: find Embree 4 and tell the linker where it is.
//!
//! Embree 4 is looked for in this order:
//! 1. `EMBREE_DIR`: a folder holding `libembree4.so` (directly or in `lib/` or `lib64/`);
//! 2. `pkg-config embree4` (Debian 13 and Ubuntu 24.04 ship it as `libembree-dev`);
//! 3. a copy this project provisions itself: the PyPI wheel `embreex==4.4.0.post1`, which
//!    carries a manylinux build of Embree 4.4 with its TBB. It is fetched with pip (binary
//!    only, explicit platform tags, so the local Python version does not matter), checked
//!    against a pinned sha256, and its two libraries are unpacked into a cache folder
//!    (`RADIOSITY_EMBREE_CACHE`, else `$XDG_CACHE_HOME/radiosity`, else `~/.cache/radiosity`).
//!
//! The folder found is added to the link search path and to the binaries' rpath, so the
//! program runs without `LD_LIBRARY_PATH`. When nothing is found the build stops with one
//! message naming the three ways.

use std::env;
use std::fs;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::Command;

/// The pinned wheel: name, version, file and sha256 as published on PyPI.
const WHEEL_REQ: &str = "embreex==4.4.0.post1";
const WHEEL_FILE: &str =
    "embreex-4.4.0.post1-cp311-cp311-manylinux_2_27_x86_64.manylinux_2_28_x86_64.whl";
const WHEEL_SHA256: &str = "2cd0f7d5c6342e6247e31f700761689cae7829454d8c6de0c41e62124a023e1f";
/// The libraries inside the wheel (auditwheel renames them with a hash suffix).
const WHEEL_EMBREE: &str = "embreex.libs/libembree4-4aef3270.so.4";
const WHEEL_TBB: &str = "embreex.libs/libtbb-dcf63f8c.so.12";
/// Folder name of the provisioned copy inside the cache.
const CACHE_SUBDIR: &str = "embree-4.4.0";

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    for var in [
        "EMBREE_DIR",
        "RADIOSITY_EMBREE_CACHE",
        "XDG_CACHE_HOME",
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
                "\nerror: Embree 4 (libembree4) was not found.\n\
                 Tried, in order:\n  \
                 1. EMBREE_DIR=<folder with libembree4.so> (set it to an Embree 4 install);\n  \
                 2. pkg-config embree4 (install Debian 13 / Ubuntu 24.04 `libembree-dev`);\n  \
                 3. provisioning {WHEEL_REQ} from PyPI with `python3 -m pip` into the cache.\n\
                 Last failure: {why}\n"
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
    provision().map(|d| (d, "provisioned"))
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

/// Returns the provisioned folder, fetching and unpacking the wheel on first use.
fn provision() -> Result<PathBuf, String> {
    if env::var("CARGO_CFG_TARGET_OS").as_deref() != Ok("linux")
        || env::var("CARGO_CFG_TARGET_ARCH").as_deref() != Ok("x86_64")
    {
        return Err("the provisioned copy exists only for x86_64 Linux".into());
    }
    let dir = cache_dir()?;
    let stamp = dir.join("READY");
    if stamp.exists() && dir.join("libembree4.so").exists() {
        return Ok(dir);
    }
    let parent = dir.parent().ok_or("bad cache folder")?;
    fs::create_dir_all(parent).map_err(|e| format!("cannot create {}: {e}", parent.display()))?;
    // Work in a private folder and rename at the end, so concurrent builds never see half.
    let work = parent.join(format!(".{CACHE_SUBDIR}.{}", std::process::id()));
    let _ = fs::remove_dir_all(&work);
    fs::create_dir_all(&work).map_err(|e| format!("cannot create {}: {e}", work.display()))?;
    let result = fetch_and_unpack(&work);
    if let Err(e) = result {
        let _ = fs::remove_dir_all(&work);
        return Err(e);
    }
    if !stamp.exists() {
        let _ = fs::remove_dir_all(&dir);
        if fs::rename(&work, &dir).is_err() && !dir.join("READY").exists() {
            return Err(format!(
                "cannot move {} to {}",
                work.display(),
                dir.display()
            ));
        }
    }
    let _ = fs::remove_dir_all(&work);
    Ok(dir)
}

/// Downloads the wheel into `work`, checks its hash, unpacks Embree and TBB, links
/// `libembree4.so` to the Embree library, and writes the `READY` stamp.
fn fetch_and_unpack(work: &Path) -> Result<(), String> {
    println!("cargo:warning=provisioning Embree 4.4 from PyPI ({WHEEL_REQ}) into the cache");
    let status = Command::new("python3")
        .args([
            "-m",
            "pip",
            "download",
            "--quiet",
            "--no-deps",
            "--only-binary=:all:",
        ])
        .args([
            "--platform",
            "manylinux_2_28_x86_64",
            "--platform",
            "manylinux2014_x86_64",
        ])
        .args([
            "--python-version",
            "3.11",
            "--implementation",
            "cp",
            "--abi",
            "cp311",
        ])
        .arg("-d")
        .arg(work)
        .arg(WHEEL_REQ)
        .status()
        .map_err(|e| format!("cannot run `python3 -m pip`: {e}"))?;
    if !status.success() {
        return Err(format!(
            "`python3 -m pip download {WHEEL_REQ}` failed ({status})"
        ));
    }
    let wheel = work.join(WHEEL_FILE);
    let digest = sha256_hex(&wheel)?;
    if digest != WHEEL_SHA256 {
        return Err(format!(
            "{} has sha256 {digest}, expected {WHEEL_SHA256}",
            wheel.display()
        ));
    }
    let unpack = work.join("wheel");
    let status = Command::new("python3")
        .args(["-m", "zipfile", "-e"])
        .arg(&wheel)
        .arg(&unpack)
        .status()
        .map_err(|e| format!("cannot run `python3 -m zipfile`: {e}"))?;
    if !status.success() {
        return Err(format!("cannot unpack {}", wheel.display()));
    }
    for lib in [WHEEL_EMBREE, WHEEL_TBB] {
        let from = unpack.join(lib);
        let name = from.file_name().ok_or("bad library name")?;
        fs::rename(&from, work.join(name))
            .map_err(|e| format!("cannot move {}: {e}", from.display()))?;
    }
    let embree_name = Path::new(WHEEL_EMBREE)
        .file_name()
        .ok_or("bad library name")?;
    std::os::unix::fs::symlink(embree_name, work.join("libembree4.so"))
        .map_err(|e| format!("cannot link libembree4.so: {e}"))?;
    let _ = fs::remove_dir_all(&unpack);
    let _ = fs::remove_file(&wheel);
    fs::write(
        work.join("READY"),
        format!("{WHEEL_REQ}\nsha256 {WHEEL_SHA256}\n"),
    )
    .map_err(|e| format!("cannot write the stamp: {e}"))
}

/// Lower-case hex sha256 of a file.
fn sha256_hex(path: &Path) -> Result<String, String> {
    use sha2::{Digest, Sha256};
    let mut file = fs::File::open(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 1 << 16];
    loop {
        let n = file
            .read(&mut buf)
            .map_err(|e| format!("{}: {e}", path.display()))?;
        if n == 0 {
            break;
        }
        hasher.update(&buf[..n]);
    }
    Ok(hasher
        .finalize()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect())
}
