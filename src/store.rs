//! A reusable form-factor folder: compute once, bake many times.
//!
//! `radiosity factors SCENE -o DIR` writes
//! - `F.mtx`: the form-factor matrix, Matrix Market coordinate real general (1-based; SciPy
//!   `scipy.io.mmread`, Julia `MatrixMarket.mmread` and sprs read it);
//! - `stderr.mtx`: the standard error of each stored entry, same pattern;
//! - `patches.csv`: one row per patch: id, area, centroid, normal, material, rho, E;
//! - `provenance.json`: estimator, seed, rays, crate version, scene, patch count and a hash
//!   of the patch geometry.
//!
//! `bake --factors DIR` reads them back and refuses a folder whose patch count or geometry
//! hash differs from the scene being baked: reflectances and emissions may change (they are
//! not part of the hash), geometry and subdivision may not.

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::Path;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::matrix::FormFactors;
use crate::mesh::PatchSet;
use crate::output::write_atomic;

/// The provenance record stored beside a matrix.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
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
fn write_mtx(path: &Path, ff: &FormFactors, values: &[f64]) -> Result<()> {
    write_mtx_in(path, ff, values, PIECE, PIECES)
}

/// [`write_mtx`] with tasks of about `piece` entries, `pieces` of them at a time.
fn write_mtx_in(
    path: &Path,
    ff: &FormFactors,
    values: &[f64],
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

/// Writes the four files of a factors folder.
pub fn write(dir: &Path, patches: &PatchSet, ff: &FormFactors) -> Result<Provenance> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    write_mtx(&dir.join("F.mtx"), ff, ff.f.data())?;
    write_mtx(&dir.join("stderr.mtx"), ff, &ff.se)?;
    let mut csv =
        String::from("id,area,cx,cy,cz,nx,ny,nz,material,rho_r,rho_g,rho_b,e_r,e_g,e_b\n");
    for i in 0..patches.len() {
        let (c, n) = (patches.centroid[i], patches.normal[i]);
        let m = &patches.materials[patches.material[i] as usize];
        let _ = writeln!(
            csv,
            "{i},{:e},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            patches.area[i],
            c.x,
            c.y,
            c.z,
            n.x,
            n.y,
            n.z,
            m.name.replace(',', "_"),
            m.rho[0],
            m.rho[1],
            m.rho[2],
            m.emit[0],
            m.emit[1],
            m.emit[2]
        );
    }
    let csv_path = dir.join("patches.csv");
    write_atomic(&csv_path, |tmp| {
        std::fs::write(tmp, &csv).map_err(|e| Error::io(tmp, e))
    })?;
    let prov = Provenance {
        writer: format!("radiosity {}", env!("CARGO_PKG_VERSION")),
        scene: patches.scene.clone(),
        patches: patches.len(),
        geometry_hash: geometry_hash(patches),
        estimator: ff.estimator.clone(),
        seed: ff.seed,
        rays: ff.rays,
        nnz: ff.f.nnz(),
        seconds: ff.seconds,
    };
    let json = serde_json::to_string_pretty(&prov).map_err(|e| Error::Output {
        path: dir.join("provenance.json"),
        msg: e.to_string(),
    })?;
    let prov_path = dir.join("provenance.json");
    write_atomic(&prov_path, |tmp| {
        std::fs::write(tmp, &json).map_err(|e| Error::io(tmp, e))
    })?;
    Ok(prov)
}

fn read_mtx(path: &Path, n: usize) -> Result<sprs::TriMat<f64>> {
    let m: sprs::TriMat<f64> = sprs::io::read_matrix_market(path).map_err(|e| Error::Parse {
        path: path.to_path_buf(),
        line: None,
        msg: format!("not a readable Matrix Market file: {e}"),
    })?;
    if m.rows() != n || m.cols() != n {
        return Err(Error::Mismatch {
            path: path.to_path_buf(),
            msg: format!(
                "matrix is {}x{}, the scene has {n} patches",
                m.rows(),
                m.cols()
            ),
        });
    }
    Ok(m)
}

/// Reads a factors folder for `patches`, refusing it when it belongs to other geometry.
pub fn read(dir: &Path, patches: &PatchSet) -> Result<FormFactors> {
    let prov_path = dir.join("provenance.json");
    let text = std::fs::read_to_string(&prov_path).map_err(|e| Error::io(&prov_path, e))?;
    let prov: Provenance = serde_json::from_str(&text).map_err(|e| Error::Parse {
        path: prov_path.clone(),
        line: Some(e.line()),
        msg: e.to_string(),
    })?;
    if prov.patches != patches.len() {
        return Err(Error::Mismatch {
            path: prov_path,
            msg: format!(
                "factors were computed for {} patches of `{}`; this scene has {} patches \
                 (use the same scene and --patches/--max-edge)",
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
    let f = read_mtx(&dir.join("F.mtx"), n)?;
    let se = read_mtx(&dir.join("stderr.mtx"), n)?;
    let f: sprs::CsMat<f64> = f.to_csr();
    let se: sprs::CsMat<f64> = se.to_csr();
    if f.indptr() != se.indptr() || f.indices() != se.indices() {
        return Err(Error::Mismatch {
            path: dir.join("stderr.mtx"),
            msg: "the standard errors do not have the pattern of F.mtx".into(),
        });
    }
    if let Some(k) = f.data().iter().position(|v| !v.is_finite() || *v < 0.0) {
        return Err(Error::Parse {
            path: dir.join("F.mtx"),
            line: None,
            msg: format!(
                "entry {k} is {} (form factors are finite and >= 0)",
                f.data()[k]
            ),
        });
    }
    Ok(FormFactors {
        se: se.data().to_vec(),
        f,
        area: patches.area.clone(),
        rays: prov.rays,
        seconds: prov.seconds,
        estimator: prov.estimator,
        seed: prov.seed,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::matrix::Entry;

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
            write_mtx_in(&path, &ff, ff.f.data(), piece, at_once).unwrap();
            let text = std::fs::read_to_string(&path).unwrap();
            let body: String = text.lines().skip(3).map(|l| format!("{l}\n")).collect();
            assert_eq!(body, want, "piece {piece}, {at_once} at once");
            assert_eq!(
                text.lines().nth(2),
                Some(format!("{n} {n} {}", ff.f.nnz()).as_str())
            );
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
