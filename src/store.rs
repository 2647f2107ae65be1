//! A reusable form-factor folder: compute once, bake many times.
//!
//! `radiosity factors SCENE -o DIR` writes
//! - the form-factor matrix and the error bar of each stored entry ([`crate::matrix::Bar`]),
//!   as two matrices of the same pattern as `F`: `stderr`, the standard error of the
//!   entry's random part (0 where its error is deterministic), and `bound`, a bound on the
//!   entry's deterministic error (0 where it is random: only the semi-analytic estimator's
//!   quadrature of unoccluded pairs makes bounds). Sum standard errors in quadrature and
//!   bounds linearly. In one of two layouts ([`Format`]):
//!   - `F.mtx`, `stderr.mtx` and `bound.mtx`: Matrix Market coordinate real general text
//!     (1-based; SciPy `scipy.io.mmread`, Julia `MatrixMarket.mmread` and sprs read it);
//!   - `F.npz`, `stderr.npz` and `bound.npz`: SciPy's sparse layout ([`crate::npz`]; read
//!     by `scipy.sparse.load_npz`), values as stored in memory: `float64` form factors,
//!     `float32` bars (the bars are kept in `f32`, so the file holds every bit of them and
//!     no more).
//!
//!   Folders written before bounds were told apart have no `bound` file: their `stderr`
//!   is read as standard errors, as it was written. A reader that knows only `stderr`
//!   sees the bounded entries' standard error 0, as for any deterministic estimate.
//! - `patches.csv`: one row per patch: id, area, centroid, normal, object, material, rho,
//!   E (names quoted as CSV quotes them when they hold a comma or a quote);
//! - `objects.csv`, `objects_F.csv`, `objects_stderr.csv`, `objects_bound.csv`: the factors
//!   between the scene's objects (area-weighted sums of the patch factors) and their
//!   standard errors and bounds, as
//!   tables named by object ([`crate::objects`]); left out, with a warning, for a scene of
//!   more than [`crate::objects::MAX_OBJECTS`] objects;
//! - `provenance.json`: the settings that shaped the matrix (estimator and its settings,
//!   seed, patch edge length, repair), crate version, scene, patch count, a hash of the
//!   patch geometry and the SHA-256 of each of the files above (its keys name the matrix
//!   files, so they also say which layout the folder holds);
//! - `manifest.json`: the run that wrote the folder (see [`crate::output::folder`]).
//!
//! The folder is written whole ([`write_folder_hashed`]): into a temporary sibling, renamed into
//! place in one step. `bake --factors DIR` reads it back and refuses a folder whose patch
//! count or geometry hash differs from the scene being baked (reflectances and emissions may
//! change, they are not part of the hash; geometry and subdivision may not), or whose files
//! are not the ones the provenance records (another run's matrix, an edited value; the
//! object tables are checked when the provenance records them: folders written before
//! they existed have none). Malformed
//! Matrix Market files are refused with the file and the first bad line, never trusted for
//! an allocation: a header's entry count is capped by what the file's length can hold, every
//! index is checked against the patch count, entries must come in the order this crate
//! writes them (row by row, columns increasing: a repeated entry is an error), form factors
//! must lie in `[0, 1]` and standard errors be finite and `>= 0`. An npz file is held to the
//! same rules, member by member ([`crate::npz::read`]: dtypes, shapes, row pointers,
//! columns), and its standard errors must repeat the pattern of `F.npz`.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::io::{BufRead, Read, Write as _};
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::error::{Error, Result};
use crate::input::open_regular;
use crate::matrix::{Bar, FormFactors};
use crate::mesh::PatchSet;
use crate::npz::{self, Compression};
use crate::objects::{ObjectFactors, MAX_OBJECTS};
use crate::output::folder::{hex, sha256_file, write_folder_hashed, ManifestFile};
use crate::output::{csv_field, write_atomic, FolderKind};
use crate::repair::Repair;

/// The folder layout version [`fn@write`] produces and [`fn@read`] accepts.
pub const FORMAT: u32 = 2;

/// Stored entries above which [`Format::Auto`] writes npz. At 2^20 entries the two text
/// files take about 55 MB and half a CPU-second to format (31 and 23 bytes an entry, as
/// measured on the 32 x 32 cube), the two npz files 21 MB (12 and 8 bytes an entry) and a
/// few hundredths of a second.
pub const AUTO_NPZ_ENTRIES: usize = 1 << 20;

/// The layout of a folder's matrix files.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// Matrix Market up to 2^20 stored entries (`AUTO_NPZ_ENTRIES`: text any tool reads,
    /// cheap at that size), npz above (where the text costs more than the factors).
    #[default]
    Auto,
    /// Matrix Market text: `F.mtx`, `stderr.mtx`.
    Mtx,
    /// SciPy's sparse npz (`scipy.sparse.load_npz`), members stored: `F.npz`,
    /// `stderr.npz`.
    Npz,
    /// SciPy's sparse npz, members deflated (smaller, slower to write and read).
    NpzDeflated,
}

impl Format {
    /// The layout written for a matrix of `nnz` stored entries (never `Auto`).
    pub fn resolve(self, nnz: usize) -> Format {
        match self {
            Format::Auto if nnz > AUTO_NPZ_ENTRIES => Format::Npz,
            Format::Auto => Format::Mtx,
            f => f,
        }
    }

    /// The files of the matrix and of its standard errors.
    pub fn files(self) -> [&'static str; 2] {
        match self {
            Format::Mtx | Format::Auto => ["F.mtx", "stderr.mtx"],
            Format::Npz | Format::NpzDeflated => ["F.npz", "stderr.npz"],
        }
    }

    /// The file of the entries' bounds (see the [module docs](self)).
    pub fn bound_file(self) -> &'static str {
        match self {
            Format::Mtx | Format::Auto => "bound.mtx",
            Format::Npz | Format::NpzDeflated => "bound.npz",
        }
    }
}

/// The object tables ([`crate::objects`]): hashed in the provenance when written, and then
/// checked by [`fn@read`].
pub const OBJECT_TABLES: [&str; 4] = [
    "objects.csv",
    "objects_F.csv",
    "objects_stderr.csv",
    "objects_bound.csv",
];

/// The provenance record stored beside a matrix.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
    /// Folder layout version ([`FORMAT`]).
    pub format: u32,
    /// Crate name and version that wrote the folder.
    pub writer: String,
    /// Scene name.
    pub scene: String,
    /// Number of patches (matrix order).
    pub patches: usize,
    /// FNV-1a hash of the patch geometry (corner positions, in patch order).
    pub geometry_hash: String,
    /// Estimator and its settings.
    pub estimator: String,
    /// Seed of the random streams.
    pub seed: u64,
    /// Rays cast.
    pub rays: u64,
    /// Stored entries.
    pub nnz: usize,
    /// Seconds the estimation took.
    pub seconds: f64,
    /// Longest patch edge of the subdivision (scene units).
    pub max_edge: f64,
    /// The repair applied after estimation (`None`, `Reciprocity`, `Closure`, `Both`).
    pub repair: String,
    /// Independent replicates behind each standard error (0, or absent in folders written
    /// before it was recorded: not known).
    #[serde(default)]
    pub replicates: usize,
    /// The bar of every entry not stored ([`FormFactors::unresolved`]: hemisphere
    /// shooting's patches no ray hit; 0, or absent in older folders, otherwise).
    #[serde(default)]
    pub unresolved: f64,
    /// SHA-256 (lower-case hex) of the matrix files ([`Format::files`]), `patches.csv`
    /// and of [`OBJECT_TABLES`] when written, by name.
    pub sha256: BTreeMap<String, String>,
    /// Why the object tables were not written (empty when they were).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub objects_skipped: String,
}

/// FNV-1a (64-bit) of the patch corner positions and corner counts, as hex.
pub fn geometry_hash(patches: &PatchSet) -> String {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut eat = |bytes: &[u8]| {
        for &b in bytes {
            h ^= b as u64;
            h = h.wrapping_mul(0x0000_0100_0000_01b3);
        }
    };
    for i in 0..patches.len() {
        let (pts, n) = patches.corner_points(i);
        eat(&(n as u32).to_le_bytes());
        // The f32 roundings of the corners: folders written before geometry became f64
        // keep their hash.
        for p in &pts[..n] {
            for c in p.as_vec3().to_array() {
                eat(&c.to_bits().to_le_bytes());
            }
        }
    }
    format!("{h:016x}")
}

/// Entries formatted by one task of [`write_mtx`] (whole rows, so a few more).
const PIECE: usize = 1 << 16;

/// Tasks formatted in parallel before their text is written out: the memory held at once is
/// about `PIECES x PIECE` lines (some 100 MB).
const PIECES: usize = 64;

/// Writes `values` (aligned with `ff.f`'s entries) as a Matrix Market file: the lines are
/// formatted in parallel, a batch of row ranges at a time, and written in row order.
fn write_mtx<V: std::fmt::LowerExp + Sync>(
    path: &Path,
    ff: &FormFactors,
    values: &[V],
    what: &str,
) -> Result<()> {
    write_mtx_in(path, ff, values, what, PIECE, PIECES)
}

/// The comment line of each matrix file: what its values are and how they add.
const F_COMMENT: &str = "F(i, j): fraction of the energy leaving patch i that reaches patch j";
/// See [`F_COMMENT`].
const SE_COMMENT: &str = "standard error of the random part of each F(i, j) (0 where \
                          its error is deterministic: see bound); add in quadrature over sums";
/// See [`F_COMMENT`].
const BOUND_COMMENT: &str = "bound on the deterministic error of each F(i, j) (0 where \
                             its error is random: see stderr); add linearly over sums";

/// [`write_mtx`] with tasks of about `piece` entries, `pieces` of them at a time.
fn write_mtx_in<V: std::fmt::LowerExp + Sync>(
    path: &Path,
    ff: &FormFactors,
    values: &[V],
    what: &str,
    piece: usize,
    pieces_at_once: usize,
) -> Result<()> {
    write_atomic(path, |tmp| {
        let file = std::fs::File::create(tmp).map_err(|e| Error::io(tmp, e))?;
        let mut w = std::io::BufWriter::new(file);
        let n = ff.len();
        let io = |e| Error::io(path, e);
        writeln!(w, "%%MatrixMarket matrix coordinate real general").map_err(io)?;
        writeln!(
            w,
            "% radiosity {}: {}",
            env!("CARGO_PKG_VERSION"),
            ff.estimator
        )
        .map_err(io)?;
        writeln!(w, "% {what}").map_err(io)?;
        writeln!(w, "{n} {n} {}", ff.f.nnz()).map_err(io)?;
        // The matrix is owned: its row pointers start at 0 and index `indices` and `values`.
        let ptr = ff.f.indptr();
        let ptr = ptr.to_proper();
        let indices = ff.f.indices();
        // Row ranges of about `piece` entries each.
        let mut pieces = Vec::new();
        let mut lo = 0;
        while lo < n {
            let mut hi = lo + 1;
            while hi < n && ptr[hi + 1] - ptr[lo] < piece {
                hi += 1;
            }
            pieces.push(lo..hi);
            lo = hi;
        }
        for batch in pieces.chunks(pieces_at_once) {
            let texts: Vec<Vec<u8>> = batch
                .par_iter()
                .map(|rows| {
                    let (a, b) = (ptr[rows.start], ptr[rows.end]);
                    let mut t = Vec::with_capacity((b - a) * 28);
                    for i in rows.clone() {
                        for k in ptr[i]..ptr[i + 1] {
                            // Writing into a vector cannot fail.
                            let _ = writeln!(t, "{} {} {:e}", i + 1, indices[k] + 1, values[k]);
                        }
                    }
                    t
                })
                .collect();
            for t in &texts {
                w.write_all(t).map_err(io)?;
            }
        }
        w.flush().map_err(io)
    })
}

/// Writes a factors folder, whole (see the [module docs](self)), its matrix in `format`
/// ([`Format::resolve`]d for the matrix). `repair` is the repair `ff` went through,
/// recorded in the provenance.
///
/// Refuses (before writing anything) a matrix with an entry outside `[0, 1]` or a standard
/// error that is negative or not finite: [`read`] would refuse it.
pub fn write(
    dir: &Path,
    patches: &PatchSet,
    ff: &FormFactors,
    repair: Repair,
    format: Format,
) -> Result<Provenance> {
    let format = format.resolve(ff.f.nnz());
    check_values(dir, ff, format)?;
    write_folder_hashed(dir, FolderKind::Factors, |tmp| {
        write_files(tmp, patches, ff, repair, format)
    })
}

/// Refuses entries [`read`] would refuse.
fn check_values(dir: &Path, ff: &FormFactors, format: Format) -> Result<()> {
    let [f_name, se_name] = format.files();
    for (i, row) in ff.f.outer_iterator().enumerate() {
        for (j, &f) in row.iter() {
            if !(0.0..=1.0).contains(&f) {
                return Err(Error::Output {
                    path: dir.join(f_name),
                    msg: format!(
                        "F({i}, {j}) is {f}, outside [0, 1]: not stored (raise --samples or \
                         --replicates)"
                    ),
                });
            }
        }
    }
    if let Some(k) = ff.se.iter().position(|&s| !Bar::of(s).is_valid()) {
        return Err(Error::Output {
            path: dir.join(se_name),
            msg: format!("error bar {k} is {}, not stored", Bar::of(ff.se[k])),
        });
    }
    Ok(())
}

/// The files of a factors folder, written into `dir`; returns the provenance and the
/// records of the files it hashed for it (all but `provenance.json`), for the manifest
/// ([`write_folder_hashed`]).
fn write_files(
    dir: &Path,
    patches: &PatchSet,
    ff: &FormFactors,
    repair: Repair,
    format: Format,
) -> Result<(Provenance, Vec<ManifestFile>)> {
    let [f_name, se_name] = format.files();
    let bound_name = format.bound_file();
    // The two parts of the bars, each 0 where the other holds.
    let (se, bound): (Vec<f32>, Vec<f32>) = ff
        .se
        .par_iter()
        .map(|&s| {
            if s.is_sign_negative() {
                (0.0, -s)
            } else {
                (s, 0.0)
            }
        })
        .unzip();
    let mut hashed: Vec<ManifestFile> = match format {
        Format::Mtx | Format::Auto => {
            write_mtx(&dir.join(f_name), ff, ff.f.data(), F_COMMENT)?;
            write_mtx(&dir.join(se_name), ff, &se, SE_COMMENT)?;
            write_mtx(&dir.join(bound_name), ff, &bound, BOUND_COMMENT)?;
            // The hashes side by side (each is one core's work).
            [f_name, se_name, bound_name]
                .par_iter()
                .map(|&name| ManifestFile::of(dir, name))
                .collect::<Result<_>>()?
        }
        Format::Npz | Format::NpzDeflated => {
            let compression = if format == Format::Npz {
                Compression::Stored
            } else {
                Compression::Deflated
            };
            let n = ff.len();
            let ptr = ff.f.indptr();
            let ptr = ptr.to_proper();
            let (f, se_path, b_path) = (dir.join(f_name), dir.join(se_name), dir.join(bound_name));
            // The files side by side: each is conversion and copying, one core's work, and
            // each is hashed (from disk) as soon as it is complete, while the others are
            // still being written.
            let (a, (b, c)) = rayon::join(
                || {
                    npz::write(&f, n, &ptr, ff.f.indices(), ff.f.data(), compression)
                        .and_then(|()| ManifestFile::of(dir, f_name))
                },
                || {
                    rayon::join(
                        || {
                            npz::write(&se_path, n, &ptr, ff.f.indices(), &se, compression)
                                .and_then(|()| ManifestFile::of(dir, se_name))
                        },
                        || {
                            npz::write(&b_path, n, &ptr, ff.f.indices(), &bound, compression)
                                .and_then(|()| ManifestFile::of(dir, bound_name))
                        },
                    )
                },
            );
            vec![a?, b?, c?]
        }
    };
    let mut csv =
        String::from("id,area,cx,cy,cz,nx,ny,nz,object,material,rho_r,rho_g,rho_b,e_r,e_g,e_b\n");
    for i in 0..patches.len() {
        let (c, n) = (patches.centroid[i], patches.normal[i]);
        let m = &patches.materials[patches.material[i] as usize];
        let _ = writeln!(
            csv,
            "{i},{:e},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            patches.area[i],
            c.x,
            c.y,
            c.z,
            n.x,
            n.y,
            n.z,
            csv_field(patches.object_name(i)),
            csv_field(&m.name),
            m.rho[0],
            m.rho[1],
            m.rho[2],
            m.emit[0],
            m.emit[1],
            m.emit[2]
        );
    }
    let text = |name: &str, body: &str| {
        write_atomic(&dir.join(name), |tmp| {
            std::fs::write(tmp, body).map_err(|e| Error::io(tmp, e))
        })
    };
    text("patches.csv", &csv)?;
    hashed.push(ManifestFile::of(dir, "patches.csv")?);
    let objects_skipped = if patches.objects.len() > MAX_OBJECTS {
        format!(
            "{} objects, more than the {MAX_OBJECTS} the object tables are made for",
            patches.objects.len()
        )
    } else {
        let o = ObjectFactors::aggregate(patches, ff)?;
        let [list, f, se, bound] = OBJECT_TABLES;
        text(list, &o.objects_csv())?;
        text(f, &o.matrix_csv(&o.f))?;
        text(se, &o.matrix_csv(&o.se))?;
        text(bound, &o.matrix_csv(&o.bound))?;
        for name in OBJECT_TABLES {
            hashed.push(ManifestFile::of(dir, name)?);
        }
        String::new()
    };
    let sha256 = hashed
        .iter()
        .map(|f| (f.name.clone(), f.sha256.clone()))
        .collect();
    let prov = Provenance {
        format: FORMAT,
        writer: format!("radiosity {}", env!("CARGO_PKG_VERSION")),
        scene: patches.scene.clone(),
        patches: patches.len(),
        geometry_hash: geometry_hash(patches),
        estimator: ff.estimator.clone(),
        seed: ff.seed,
        rays: ff.rays,
        nnz: ff.f.nnz(),
        seconds: ff.seconds,
        max_edge: patches.max_edge,
        repair: format!("{repair:?}"),
        replicates: ff.replicates,
        unresolved: ff.unresolved,
        sha256,
        objects_skipped,
    };
    let prov_path = dir.join("provenance.json");
    crate::output::write_json(&prov_path, &prov)?;
    Ok((prov, hashed))
}

/// Longest `provenance.json` read (it is a few hundred bytes).
const MAX_PROVENANCE_BYTES: u64 = 1 << 20;

/// Longest line of a Matrix Market file read (an entry line is under 60 bytes).
const MAX_LINE: usize = 1024;

/// Shortest entry line: `1 1 0` and a newline.
const MIN_ENTRY_BYTES: u64 = 6;

/// A matrix read by [`parse_mtx`], in CSR arrays.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MtxRows {
    /// Row pointers (`n + 1`).
    pub indptr: Vec<usize>,
    /// Column of each entry (0-based).
    pub indices: Vec<u32>,
    /// Value of each entry.
    pub data: Vec<f64>,
    /// SHA-256 of the bytes read, lower-case hex.
    pub sha256: String,
}

/// Which values a Matrix Market file of a factors folder may hold.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Values {
    /// Form factors: in `[0, 1]`.
    FormFactors,
    /// Standard errors: finite and `>= 0`.
    StdErrors,
}

/// A reader that hashes what passes through it.
struct Hashing<R> {
    inner: R,
    hasher: Sha256,
}

impl<R: Read> Read for Hashing<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let k = self.inner.read(buf)?;
        self.hasher.update(&buf[..k]);
        Ok(k)
    }
}

/// Parses a Matrix Market file of a factors folder: `coordinate real general`, `n x n`,
/// entries row by row with increasing columns, as [`fn@write`] makes them. `bytes` is the
/// file's length (it caps the header's entry count); `pattern`, when given, is the
/// `(indptr, indices)` the entries must repeat (stderr.mtx follows F.mtx). `path` names the
/// file in messages. Everything is read, so the hash covers the whole file.
pub fn parse_mtx(
    path: &Path,
    input: impl Read,
    bytes: u64,
    n: usize,
    values: Values,
    pattern: Option<(&[usize], &[u32])>,
) -> Result<MtxRows> {
    let mut r = std::io::BufReader::new(Hashing {
        inner: input,
        hasher: Sha256::new(),
    });
    let mut line_no = 0usize;
    let mut buf = Vec::with_capacity(128);
    let bad = |line: usize, msg: String| Error::Parse {
        path: path.to_path_buf(),
        line: Some(line),
        msg,
    };
    // The next line without its end; `None` at the end of the file.
    let mut next_line = |r: &mut std::io::BufReader<Hashing<_>>, line_no: &mut usize| {
        buf.clear();
        let k = r
            .by_ref()
            .take(MAX_LINE as u64 + 1)
            .read_until(b'\n', &mut buf)
            .map_err(|e| Error::io(path, e))?;
        if k == 0 {
            return Ok(None);
        }
        *line_no += 1;
        if buf.last() == Some(&b'\n') {
            buf.pop();
        } else if buf.len() > MAX_LINE {
            return Err(bad(*line_no, format!("line longer than {MAX_LINE} bytes")));
        }
        match std::str::from_utf8(&buf) {
            Ok(t) => Ok(Some(t.trim_end_matches('\r').to_string())),
            Err(_) => Err(bad(*line_no, "not text (invalid UTF-8)".into())),
        }
    };
    let header = next_line(&mut r, &mut line_no)?
        .ok_or_else(|| bad(1, "empty file, not Matrix Market".into()))?;
    let words: Vec<String> = header
        .split_whitespace()
        .map(|w| w.to_ascii_lowercase())
        .collect();
    if words.first().map(String::as_str) != Some("%%matrixmarket") {
        return Err(bad(
            1,
            "no `%%MatrixMarket` header: not a Matrix Market file".into(),
        ));
    }
    if words[1..] != ["matrix", "coordinate", "real", "general"] {
        return Err(bad(
            1,
            format!(
                "header `{header}`: a factors folder holds `matrix coordinate real general` \
                 matrices only"
            ),
        ));
    }
    let size = loop {
        match next_line(&mut r, &mut line_no)? {
            None => return Err(bad(line_no, "no size line `ROWS COLS ENTRIES`".into())),
            Some(l) if l.starts_with('%') || l.trim().is_empty() => continue,
            Some(l) => break l,
        }
    };
    let dims: Vec<u64> = size
        .split_whitespace()
        .map(|w| w.parse::<u64>())
        .collect::<std::result::Result<_, _>>()
        .ok()
        .filter(|d: &Vec<u64>| d.len() == 3)
        .ok_or_else(|| {
            bad(
                line_no,
                format!("size line `{size}`: expected ROWS COLS ENTRIES"),
            )
        })?;
    if dims[0] != n as u64 || dims[1] != n as u64 {
        return Err(Error::Mismatch {
            path: path.to_path_buf(),
            msg: format!(
                "matrix is {}x{}, the scene has {n} patches",
                dims[0], dims[1]
            ),
        });
    }
    let nnz = dims[2];
    if nnz > bytes / MIN_ENTRY_BYTES || nnz > (n as u64).saturating_mul(n as u64) {
        return Err(bad(
            line_no,
            format!(
                "the header announces {nnz} entries; a {n} x {n} matrix in a file of {bytes} \
                 bytes holds at most {}",
                (bytes / MIN_ENTRY_BYTES).min((n as u64).saturating_mul(n as u64))
            ),
        ));
    }
    let nnz = nnz as usize;
    let mut m = MtxRows {
        indptr: Vec::with_capacity(n + 1),
        indices: Vec::with_capacity(nnz),
        data: Vec::with_capacity(nnz),
        sha256: String::new(),
    };
    m.indptr.push(0);
    let mut prev: Option<(usize, usize)> = None;
    while let Some(l) = next_line(&mut r, &mut line_no)? {
        if l.starts_with('%') || l.trim().is_empty() {
            continue;
        }
        let k = m.data.len();
        if k == nnz {
            return Err(bad(
                line_no,
                format!("more entries than the header's {nnz}"),
            ));
        }
        let mut w = l.split_whitespace();
        let (Some(a), Some(b), Some(v), None) = (w.next(), w.next(), w.next(), w.next()) else {
            return Err(bad(line_no, format!("`{l}`: expected ROW COLUMN VALUE")));
        };
        let index = |t: &str| t.parse::<usize>().ok().filter(|&x| x >= 1 && x <= n);
        let (Some(i), Some(j)) = (index(a), index(b)) else {
            return Err(bad(
                line_no,
                format!("`{l}`: row and column must be integers in 1..={n}"),
            ));
        };
        let (i, j) = (i - 1, j - 1);
        let value: f64 = v
            .parse()
            .map_err(|_| bad(line_no, format!("`{v}` is not a number")))?;
        let ok = match values {
            Values::FormFactors => (0.0..=1.0).contains(&value),
            Values::StdErrors => value.is_finite() && value >= 0.0,
        };
        if !ok {
            return Err(bad(
                line_no,
                match values {
                    Values::FormFactors => {
                        format!("F({i}, {j}) = {v} (a form factor lies in [0, 1])")
                    }
                    Values::StdErrors => {
                        format!("standard error {v} (must be finite and >= 0)")
                    }
                },
            ));
        }
        match prev {
            Some(p) if p == (i, j) => {
                return Err(bad(
                    line_no,
                    format!("entry ({a}, {b}) repeats the line before"),
                ))
            }
            Some(p) if p > (i, j) => {
                return Err(bad(
                    line_no,
                    format!(
                        "entry ({a}, {b}) after ({}, {}): entries must come row by row, \
                         columns increasing (each entry once)",
                        p.0 + 1,
                        p.1 + 1
                    ),
                ))
            }
            _ => {}
        }
        prev = Some((i, j));
        if let Some((ptr, ind)) = pattern {
            if ind.get(k) != Some(&(j as u32)) || !(ptr[i] <= k && k < ptr[i + 1]) {
                return Err(Error::Mismatch {
                    path: path.to_path_buf(),
                    msg: format!(
                        "line {line_no}: entry ({a}, {b}) is not entry {} of F.mtx: the \
                         standard errors do not have the pattern of F.mtx",
                        k + 1
                    ),
                });
            }
        }
        while m.indptr.len() <= i {
            m.indptr.push(k);
        }
        m.indices.push(j as u32);
        m.data.push(value);
    }
    if m.data.len() != nnz {
        return Err(bad(
            line_no,
            format!(
                "the file ends after {} of the header's {nnz} entries",
                m.data.len()
            ),
        ));
    }
    while m.indptr.len() <= n {
        m.indptr.push(nnz);
    }
    m.sha256 = hex(&r.into_inner().hasher.finalize());
    Ok(m)
}

/// Reads a Matrix Market file of the folder (see [`parse_mtx`]).
fn read_mtx(
    path: &Path,
    n: usize,
    values: Values,
    pattern: Option<(&[usize], &[u32])>,
) -> Result<MtxRows> {
    let (file, bytes) = open_regular(path)?;
    parse_mtx(path, file.take(bytes), bytes, n, values, pattern)
}

/// The layout of a folder's matrix files, from the names its provenance hashes.
fn stored_format(prov_path: &Path, prov: &Provenance) -> Result<Format> {
    let has = |format: Format| format.files().iter().all(|f| prov.sha256.contains_key(*f));
    match (has(Format::Mtx), has(Format::Npz)) {
        (true, false) => Ok(Format::Mtx),
        (false, true) => Ok(Format::Npz),
        _ => Err(Error::Mismatch {
            path: prov_path.to_path_buf(),
            msg: format!(
                "records the SHA-256 of {}: expected F.mtx and stderr.mtx, or F.npz and \
                 stderr.npz (run `radiosity factors` again)",
                prov.sha256.keys().cloned().collect::<Vec<_>>().join(", ")
            ),
        }),
    }
}

/// Reads an npz file of the folder ([`npz::read`]) with the SHA-256 of its bytes, and
/// refuses values a form factor or a standard error cannot have.
fn read_npz<V: npz::Value + Into<f64>>(
    path: &Path,
    n: usize,
    values: Values,
) -> Result<(npz::CsrArrays<V>, String)> {
    let (file, bytes) = open_regular(path)?;
    let mut input = Hashing {
        inner: std::io::BufReader::with_capacity(1 << 20, file.take(bytes)),
        hasher: Sha256::new(),
    };
    let m = npz::read::<V>(path, &mut input, bytes, n)?;
    for i in 0..n {
        for k in m.indptr[i]..m.indptr[i + 1] {
            let v: f64 = m.data[k].into();
            let (ok, what) = match values {
                Values::FormFactors => ((0.0..=1.0).contains(&v), "a form factor lies in [0, 1]"),
                Values::StdErrors => (
                    v.is_finite() && v >= 0.0,
                    "a standard error is finite and >= 0",
                ),
            };
            if !ok {
                let j = m.indices[k];
                return Err(Error::Parse {
                    path: path.to_path_buf(),
                    line: None,
                    msg: format!("data.npy: entry {k}, ({i}, {j}), is {v} ({what})"),
                });
            }
        }
    }
    Ok((m, hex(&input.hasher.finalize())))
}

/// Folds the bounds read from `path` into the standard errors `se` (same pattern) as
/// stored bars ([`Bar::stored`]): an entry with a bound holds it (its standard error must
/// be 0: this crate writes one part per entry).
fn join_bounds(path: &Path, se: &mut [f32], bounds: impl Iterator<Item = f32>) -> Result<()> {
    for (k, (s, b)) in se.iter_mut().zip(bounds).enumerate() {
        if b > 0.0 {
            if *s != 0.0 {
                return Err(Error::Parse {
                    path: path.to_path_buf(),
                    line: None,
                    msg: format!(
                        "entry {k} has both a bound ({b:e}) and a standard error ({s:e}): \
                         each entry's bar is one or the other"
                    ),
                });
            }
            *s = -b;
        }
    }
    Ok(())
}

/// Refuses a file whose SHA-256 is not the one the provenance records.
fn check_hash(dir: &Path, prov: &Provenance, name: &str, sha256: &str) -> Result<()> {
    match prov.sha256.get(name) {
        Some(want) if want == sha256 => Ok(()),
        want => Err(Error::Mismatch {
            path: dir.join(name),
            msg: format!(
                "SHA-256 {sha256}, provenance.json records {}: the file was changed or comes \
                 from another run (run `radiosity factors` again)",
                want.map_or("none", String::as_str)
            ),
        }),
    }
}

/// Parses `provenance.json` text (`path` names it in messages).
pub fn parse_provenance(path: &Path, text: &str) -> Result<Provenance> {
    let prov: Provenance = serde_json::from_str(text).map_err(|e| Error::Parse {
        path: path.to_path_buf(),
        line: Some(e.line()),
        msg: format!(
            "{e} (not a factors folder of radiosity {}: run `radiosity factors` again)",
            env!("CARGO_PKG_VERSION")
        ),
    })?;
    if prov.format != FORMAT {
        return Err(Error::Mismatch {
            path: path.to_path_buf(),
            msg: format!(
                "folder format {} (this version reads {FORMAT}): run `radiosity factors` again",
                prov.format
            ),
        });
    }
    Ok(prov)
}

/// Reads a factors folder for `patches`, refusing it when it belongs to other geometry or
/// any of its files is not the one its provenance records.
pub fn read(dir: &Path, patches: &PatchSet) -> Result<FormFactors> {
    read_located(dir, patches).map(|(ff, _)| ff)
}

/// [`read`], with the path of the matrix file read (`F.mtx` or `F.npz`), for messages
/// about the matrix.
pub fn read_located(dir: &Path, patches: &PatchSet) -> Result<(FormFactors, PathBuf)> {
    let prov_path = dir.join("provenance.json");
    let (file, bytes) = open_regular(&prov_path)?;
    if bytes > MAX_PROVENANCE_BYTES {
        return Err(Error::Parse {
            path: prov_path,
            line: None,
            msg: format!("{bytes} bytes: too long for a provenance record"),
        });
    }
    let mut text = String::new();
    file.take(MAX_PROVENANCE_BYTES)
        .read_to_string(&mut text)
        .map_err(|e| Error::io(&prov_path, e))?;
    let prov = parse_provenance(&prov_path, &text)?;
    if prov.patches != patches.len() {
        return Err(Error::Mismatch {
            path: prov_path,
            msg: format!(
                "factors were computed for {} patches of `{}`; this scene has {} patches \
                 (use the same scene, --patches/--max-edge and --two-sided)",
                prov.patches,
                prov.scene,
                patches.len()
            ),
        });
    }
    let hash = geometry_hash(patches);
    if prov.geometry_hash != hash {
        return Err(Error::Mismatch {
            path: prov_path,
            msg: format!(
                "factors were computed for other geometry (hash {} of `{}`, this scene has \
                 {hash}); only reflectances and emissions may change between runs",
                prov.geometry_hash, prov.scene
            ),
        });
    }
    let n = patches.len();
    let csv_path = dir.join("patches.csv");
    open_regular(&csv_path)?;
    check_hash(dir, &prov, "patches.csv", &sha256_file(&csv_path)?.1)?;
    for name in OBJECT_TABLES {
        if prov.sha256.contains_key(name) {
            let path = dir.join(name);
            open_regular(&path)?;
            check_hash(dir, &prov, name, &sha256_file(&path)?.1)?;
        }
    }
    let format = stored_format(&prov_path, &prov)?;
    let [f_name, se_name] = format.files();
    let f_path = dir.join(f_name);
    let (indptr, indices, data, se) = match format {
        Format::Mtx | Format::Auto => {
            let f = read_mtx(&f_path, n, Values::FormFactors, None)?;
            check_hash(dir, &prov, f_name, &f.sha256)?;
            let se = read_mtx(
                &dir.join(se_name),
                n,
                Values::StdErrors,
                Some((&f.indptr, &f.indices)),
            )?;
            check_hash(dir, &prov, se_name, &se.sha256)?;
            let mut se: Vec<f32> = se.data.iter().map(|&s| s as f32).collect();
            let b_name = format.bound_file();
            if prov.sha256.contains_key(b_name) {
                let b = read_mtx(
                    &dir.join(b_name),
                    n,
                    Values::StdErrors,
                    Some((&f.indptr, &f.indices)),
                )?;
                check_hash(dir, &prov, b_name, &b.sha256)?;
                join_bounds(&dir.join(b_name), &mut se, b.data.iter().map(|&b| b as f32))?;
            }
            (f.indptr, f.indices, f.data, se)
        }
        Format::Npz | Format::NpzDeflated => {
            let (f, sha) = read_npz::<f64>(&f_path, n, Values::FormFactors)?;
            check_hash(dir, &prov, f_name, &sha)?;
            let se_path = dir.join(se_name);
            let (se, sha) = read_npz::<f32>(&se_path, n, Values::StdErrors)?;
            if se.indptr != f.indptr || se.indices != f.indices {
                return Err(Error::Mismatch {
                    path: se_path,
                    msg: format!("the standard errors do not have the pattern of {f_name}"),
                });
            }
            check_hash(dir, &prov, se_name, &sha)?;
            let mut se = se.data;
            let b_name = format.bound_file();
            if prov.sha256.contains_key(b_name) {
                let b_path = dir.join(b_name);
                let (b, sha) = read_npz::<f32>(&b_path, n, Values::StdErrors)?;
                if b.indptr != f.indptr || b.indices != f.indices {
                    return Err(Error::Mismatch {
                        path: b_path,
                        msg: format!("the bounds do not have the pattern of {f_name}"),
                    });
                }
                check_hash(dir, &prov, b_name, &sha)?;
                join_bounds(&b_path, &mut se, b.data.into_iter())?;
            }
            (f.indptr, f.indices, f.data, se)
        }
    };
    let f =
        crate::matrix::Csr::try_new((n, n), indptr, indices, data).map_err(|e| Error::Parse {
            path: f_path.clone(),
            line: None,
            msg: format!("not a valid sparse matrix: {}", e.3),
        })?;
    let ff = FormFactors {
        se,
        f,
        area: patches.area.clone(),
        rays: prov.rays,
        seconds: prov.seconds,
        estimator: prov.estimator,
        seed: prov.seed,
        replicates: prov.replicates,
        unresolved: prov.unresolved,
    };
    Ok((ff, f_path))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::matrix::Entry;

    /// A valid 3 x 3 F.mtx body with `extra` lines appended and the header's count `nnz`.
    fn mtx(header: &str, nnz: &str, entries: &str) -> String {
        format!("%%MatrixMarket matrix coordinate {header}\n% comment\n3 3 {nnz}\n{entries}")
    }

    fn parse(text: &str, values: Values) -> Result<MtxRows> {
        let p = Path::new("F.mtx");
        parse_mtx(p, text.as_bytes(), text.len() as u64, 3, values, None)
    }

    #[test]
    fn malformed_matrix_market_is_refused_with_its_line() {
        let good = "1 2 5e-1\n1 3 2.5e-1\n3 1 1e0\n";
        let m = parse(&mtx("real general", "3", good), Values::FormFactors).unwrap();
        assert_eq!(m.indptr, [0, 2, 2, 3]);
        assert_eq!(m.indices, [1, 2, 0]);
        assert_eq!(m.data, [0.5, 0.25, 1.0]);
        let cases: [(String, &str); 12] = [
            (mtx("real symmetric", "3", good), "F.mtx:1: header"),
            (
                mtx("real general", "3", "1 2 0.5\n4 3 0.1\n3 1 1\n"),
                "F.mtx:5:",
            ),
            (
                mtx("real general", "3", "1 2 0.5\n1 0 0.1\n3 1 1\n"),
                "F.mtx:5:",
            ),
            (
                mtx("real general", "1000000000000000000", good),
                "header announces",
            ),
            (
                mtx("real general", "3", "1 2 0.5\n1 2 0.5\n3 1 1\n"),
                "F.mtx:5: entry (1, 2) repeats",
            ),
            (
                mtx("real general", "3", "1 3 0.5\n1 2 0.5\n3 1 1\n"),
                "F.mtx:5: entry (1, 2) after (1, 3)",
            ),
            (
                mtx("real general", "3", "1 2 5\n1 3 0.5\n3 1 1\n"),
                "F.mtx:4: F(0, 1) = 5",
            ),
            (
                mtx("real general", "3", "1 2 NaN\n1 3 0.5\n3 1 1\n"),
                "F.mtx:4:",
            ),
            (
                mtx("real general", "3", "1 2 -0.1\n1 3 0.5\n3 1 1\n"),
                "F.mtx:4:",
            ),
            (
                mtx("real general", "4", good),
                "ends after 3 of the header's 4",
            ),
            (mtx("real general", "2", good), "F.mtx:6: more entries"),
            (
                mtx("real general", "3", "1 2 0.5 7\n1 3 0.5\n3 1 1\n"),
                "F.mtx:4:",
            ),
        ];
        for (text, want) in cases {
            let e = parse(&text, Values::FormFactors).unwrap_err().to_string();
            assert!(e.contains(want), "{text}\n  got {e}\n  expected {want}");
        }
        let e = parse(&mtx("real general", "1", "1 2 inf\n"), Values::StdErrors)
            .unwrap_err()
            .to_string();
        assert!(e.contains("F.mtx:4: standard error inf"), "{e}");
        // A shape other than the scene's is a mismatch, not a parse error.
        let e = parse(
            "%%MatrixMarket matrix coordinate real general\n4 4 0\n",
            Values::FormFactors,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("matrix is 4x4, the scene has 3 patches"), "{e}");
        // No newline for gigabytes is refused at the first long line, not read to the end.
        let long = format!("%%MatrixMarket{}", " ".repeat(5000));
        let e = parse(&long, Values::FormFactors).unwrap_err().to_string();
        assert!(e.contains("F.mtx:1: line longer than"), "{e}");
    }

    #[test]
    fn a_device_is_not_read_as_a_matrix() {
        let e = read_mtx(Path::new("/dev/zero"), 3, Values::FormFactors, None)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("/dev/zero") && e.contains("not a regular file"),
            "{e}"
        );
    }

    #[test]
    fn matrix_market_text_does_not_depend_on_the_pieces() {
        // Rows of 0 to 6 entries, empty rows included, written whole, in pieces of one row
        // or a few entries, one or two pieces at a time: the same file, line by line as
        // the rows list them.
        let n = 9;
        let rows: Vec<Vec<Entry>> = (0..n)
            .map(|i| {
                (0..(i * 5) % 7)
                    .map(|j| Entry {
                        j: j as u32,
                        f: (i * 10 + j) as f64 / 97.0,
                        se: 1e-3 / (j + 1) as f64,
                    })
                    .collect()
            })
            .collect();
        let mut want = String::new();
        for (i, r) in rows.iter().enumerate() {
            for e in r {
                let _ = writeln!(want, "{} {} {:e}", i + 1, e.j + 1, e.f);
            }
        }
        let ff = FormFactors::from_rows(rows, vec![1.0; n], 0, 0.0, "test".into(), 0);
        let dir = std::env::temp_dir().join(format!("radiosity-mtx-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("F.mtx");
        for (piece, at_once) in [(PIECE, PIECES), (1, 1), (3, 2), (4, 64)] {
            write_mtx_in(&path, &ff, ff.f.data(), F_COMMENT, piece, at_once).unwrap();
            let text = std::fs::read_to_string(&path).unwrap();
            let body: String = text.lines().skip(4).map(|l| format!("{l}\n")).collect();
            assert_eq!(body, want, "piece {piece}, {at_once} at once");
            assert_eq!(text.lines().nth(2), Some(format!("% {F_COMMENT}").as_str()));
            assert_eq!(
                text.lines().nth(3),
                Some(format!("{n} {n} {}", ff.f.nnz()).as_str())
            );
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
