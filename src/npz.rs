//! CSR matrices in SciPy's own sparse `.npz` layout: what `scipy.sparse.save_npz` writes
//! for a `csr_matrix`, so that `scipy.sparse.load_npz("F.npz")` reads the file with no
//! code of ours.
//!
//! The layout, as `scipy/sparse/_matrix_io.py` (SciPy 1.17) writes it: a zip archive
//! (members stored, or deflated as `save_npz`'s default `compressed=True` makes them) of
//! five `.npy` arrays, in this order:
//!
//! | member | dtype | shape | content |
//! |---|---|---|---|
//! | `indices.npy` | `<i4` (`<i8` past 2^31 - 1 entries or columns) | `(nnz,)` | column of each entry, increasing within a row |
//! | `indptr.npy` | as `indices.npy` | `(n + 1,)` | row pointers, from 0 to `nnz` |
//! | `format.npy` | `\|S3` | `()` | the bytes `b'csr'` (`save_npz` stores `format.encode('ascii')`; `load_npz` also takes a `<U3` string, and so does [`read`]) |
//! | `shape.npy` | `<i8` | `(2,)` | rows, columns |
//! | `data.npy` | `<f8` or `<f4` | `(nnz,)` | the values |
//!
//! There is no `_is_array` member (SciPy writes one for `csr_array` only): `load_npz`
//! returns a `csr_matrix`. Index dtypes follow SciPy's rule (32-bit while every index and
//! the entry count fit, else 64-bit for both); the reader takes either for either.
//!
//! The container is the `zip` crate (zip-rs: pure Rust, CRC-32 checked on reading,
//! deflate through flate2 on zlib-rs; version 7.3, the last for Rust 1.83). The `.npy`
//! headers (a magic string and a Python dictionary literal of three keys) are written and
//! parsed here rather than through a crate such as `npyz` or `ndarray-npy`: those convert
//! into their own array types and accept any dtype they know, where this layout needs the
//! arrays streamed from the slices the matrix already holds (no second copy of hundreds
//! of megabytes), a reader that refuses every dtype but the few above, and allocations
//! bounded by the file's length.
//!
//! [`read`] goes through the archive front to back from any [`Read`]
//! ([`zip::read::read_zipfile_from_stream`]), so a caller can hash the bytes as they pass
//! (the factors folder checks them against its provenance) without holding the file in
//! memory. It refuses, naming the member: a file that is not a zip, or one cut short (the
//! end-of-central-directory record must close it); a member other than the five, or one
//! twice; a compression other than stored or deflated; a CRC mismatch; a `.npy` header
//! that does not parse, another dtype, byte order or shape than the table's; array bytes
//! other than the header describes; a shape other than `(n, n)`; row pointers that do not
//! run from 0 to `nnz` without decreasing; a column outside `0..n`, or not increasing
//! within its row (so no entry repeats). Values are not judged here: [`crate::store`]
//! checks what a form factor or a standard error may be.

use std::io::{BufWriter, Read, Write};
use std::path::Path;

use zip::write::SimpleFileOptions;
use zip::{CompressionMethod, ZipWriter};

use crate::error::{Error, Result};
use crate::output::write_atomic;

/// How the members of an archive are stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Compression {
    /// As they are (`np.savez`, `save_npz(..., compressed=False)`).
    Stored,
    /// Deflated at [`DEFLATE_LEVEL`] (`np.savez_compressed`, `save_npz`'s default).
    Deflated,
}

/// zlib level of [`Compression::Deflated`] (NumPy's `savez_compressed` uses zlib's
/// default, 6; level 1 is several times faster on form factors and loses little).
pub const DEFLATE_LEVEL: i64 = 1;

/// A value type of `data.npy`.
pub trait Value: Copy + Send + Sync + 'static {
    /// NumPy's dtype string (`<f8`).
    const DESCR: &'static str;
    /// Bytes per value.
    const SIZE: usize;
    /// Appends the little-endian bytes of `self`.
    fn put(self, out: &mut Vec<u8>);
    /// The value of `SIZE` little-endian bytes.
    fn get(bytes: &[u8]) -> Self;
}

impl Value for f64 {
    const DESCR: &'static str = "<f8";
    const SIZE: usize = 8;
    fn put(self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.to_le_bytes());
    }
    fn get(bytes: &[u8]) -> Self {
        let mut b = [0u8; 8];
        b.copy_from_slice(bytes);
        f64::from_le_bytes(b)
    }
}

impl Value for f32 {
    const DESCR: &'static str = "<f4";
    const SIZE: usize = 4;
    fn put(self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.to_le_bytes());
    }
    fn get(bytes: &[u8]) -> Self {
        let mut b = [0u8; 4];
        b.copy_from_slice(bytes);
        f32::from_le_bytes(b)
    }
}

/// The members of the layout, in SciPy's order.
pub const MEMBERS: [&str; 5] = [
    "indices.npy",
    "indptr.npy",
    "format.npy",
    "shape.npy",
    "data.npy",
];

/// Values converted per write (a buffer of 512 KiB at 8 bytes a value).
const CHUNK: usize = 1 << 16;

/// Whether SciPy keeps the indices of an `n x n` matrix of `nnz` entries in 32 bits.
fn narrow(n: usize, nnz: usize) -> bool {
    n <= i32::MAX as usize && nnz <= i32::MAX as usize
}

/// A `.npy` version 1.0 header for `descr` and `shape`, padded with spaces to a multiple
/// of 64 bytes as NumPy pads it.
fn npy_header(descr: &str, shape: &[usize]) -> Vec<u8> {
    let shape = match shape {
        [] => "()".to_string(),
        [a] => format!("({a},)"),
        s => format!(
            "({})",
            s.iter()
                .map(|d| d.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let mut dict = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    let unpadded = 10 + dict.len() + 1;
    dict.extend(std::iter::repeat_n(
        ' ',
        unpadded.next_multiple_of(64) - unpadded,
    ));
    dict.push('\n');
    let mut h = b"\x93NUMPY\x01\x00".to_vec();
    // The dictionary above is under 200 bytes: it fits version 1.0's 16-bit length.
    h.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    h.extend_from_slice(dict.as_bytes());
    h
}

/// Writes `items` through `put`, [`CHUNK`] at a time.
fn put_all<T: Copy>(
    w: &mut impl Write,
    items: &[T],
    size: usize,
    put: impl Fn(T, &mut Vec<u8>),
) -> std::io::Result<()> {
    let mut buf = Vec::with_capacity(CHUNK * size);
    for c in items.chunks(CHUNK) {
        buf.clear();
        for &x in c {
            put(x, &mut buf);
        }
        w.write_all(&buf)?;
    }
    Ok(())
}

/// Writes the `n x n` CSR matrix `(indptr, indices, data)` to `path` in SciPy's layout
/// (see the [module docs](self)), whole or not at all ([`write_atomic`]). The arrays must
/// be a valid CSR matrix (as `sprs` keeps them); the same arrays give the same bytes.
pub fn write<V: Value>(
    path: &Path,
    n: usize,
    indptr: &[usize],
    indices: &[u32],
    data: &[V],
    compression: Compression,
) -> Result<()> {
    let nnz = data.len();
    debug_assert!(indptr.len() == n + 1 && indices.len() == nnz);
    write_atomic(path, |tmp| {
        let io = |e: std::io::Error| Error::io(tmp, e);
        let zip = |e: zip::result::ZipError| Error::Output {
            path: tmp.to_path_buf(),
            msg: format!("zip archive: {e}"),
        };
        let file = std::fs::File::create(tmp).map_err(io)?;
        let mut z = ZipWriter::new(BufWriter::with_capacity(1 << 20, file));
        let start = |z: &mut ZipWriter<_>, name: &str, bytes: usize| {
            let options = SimpleFileOptions::default()
                .compression_method(match compression {
                    Compression::Stored => CompressionMethod::Stored,
                    Compression::Deflated => CompressionMethod::Deflated,
                })
                .compression_level(match compression {
                    Compression::Stored => None,
                    Compression::Deflated => Some(DEFLATE_LEVEL),
                })
                // ZIP64 sizes past 2 GiB (deflate may grow incompressible data a little).
                .large_file(bytes > 1 << 31);
            z.start_file(name, options).map_err(zip)
        };
        let (index, width) = if narrow(n, nnz) {
            ("<i4", 4)
        } else {
            ("<i8", 8)
        };
        let header = npy_header(index, &[nnz]);
        start(&mut z, "indices.npy", header.len() + nnz * width)?;
        z.write_all(&header).map_err(io)?;
        if width == 4 {
            put_all(&mut z, indices, 4, |j, b| {
                b.extend_from_slice(&(j as i32).to_le_bytes())
            })
        } else {
            put_all(&mut z, indices, 8, |j, b| {
                b.extend_from_slice(&(j as i64).to_le_bytes())
            })
        }
        .map_err(io)?;
        let header = npy_header(index, &[n + 1]);
        start(&mut z, "indptr.npy", header.len() + (n + 1) * width)?;
        z.write_all(&header).map_err(io)?;
        if width == 4 {
            put_all(&mut z, indptr, 4, |p, b| {
                b.extend_from_slice(&(p as i32).to_le_bytes())
            })
        } else {
            put_all(&mut z, indptr, 8, |p, b| {
                b.extend_from_slice(&(p as i64).to_le_bytes())
            })
        }
        .map_err(io)?;
        let header = npy_header("|S3", &[]);
        start(&mut z, "format.npy", header.len() + 3)?;
        z.write_all(&header).map_err(io)?;
        z.write_all(b"csr").map_err(io)?;
        let header = npy_header("<i8", &[2]);
        start(&mut z, "shape.npy", header.len() + 16)?;
        z.write_all(&header).map_err(io)?;
        for d in [n, n] {
            z.write_all(&(d as i64).to_le_bytes()).map_err(io)?;
        }
        let header = npy_header(V::DESCR, &[nnz]);
        start(&mut z, "data.npy", header.len() + nnz * V::SIZE)?;
        z.write_all(&header).map_err(io)?;
        put_all(&mut z, data, V::SIZE, V::put).map_err(io)?;
        let w = z.finish().map_err(zip)?;
        w.into_inner().map_err(|e| io(e.into_error()))?;
        Ok(())
    })
}

/// A matrix read by [`read`], in CSR arrays.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CsrArrays<V> {
    /// Row pointers (`n + 1`).
    pub indptr: Vec<usize>,
    /// Column of each entry.
    pub indices: Vec<u32>,
    /// Value of each entry.
    pub data: Vec<V>,
}

/// A `.npy` header's dictionary.
#[derive(Clone, Debug, PartialEq)]
struct NpyHeader {
    descr: String,
    fortran_order: bool,
    shape: Vec<u64>,
}

/// A value of a `.npy` header's dictionary literal.
#[derive(Clone, Debug, PartialEq)]
enum Literal {
    Str(String),
    Bool(bool),
    Tuple(Vec<u64>),
}

/// Parses the dictionary literal of a `.npy` header: `{'descr': '<f8', 'fortran_order':
/// False, 'shape': (3,), }` and the like (single or double quotes, any spacing, a
/// trailing comma or none), with exactly those three keys.
fn parse_dict(text: &str) -> std::result::Result<NpyHeader, String> {
    let b = text.as_bytes();
    let mut k = 0;
    let skip = |k: &mut usize| {
        while *k < b.len() && b[*k].is_ascii_whitespace() {
            *k += 1;
        }
    };
    let expect = |k: &mut usize, c: u8| -> std::result::Result<(), String> {
        skip(k);
        if b.get(*k) == Some(&c) {
            *k += 1;
            Ok(())
        } else {
            Err(format!("expected `{}` at byte {}", c as char, *k))
        }
    };
    let string = |k: &mut usize| -> std::result::Result<String, String> {
        skip(k);
        let q = match b.get(*k) {
            Some(&q @ (b'\'' | b'"')) => q,
            _ => return Err(format!("expected a quoted string at byte {}", *k)),
        };
        let from = *k + 1;
        let len = b[from..]
            .iter()
            .position(|&c| c == q)
            .ok_or("unterminated string")?;
        *k = from + len + 1;
        Ok(text[from..from + len].to_string())
    };
    expect(&mut k, b'{')?;
    let mut entries: Vec<(String, Literal)> = Vec::new();
    loop {
        skip(&mut k);
        if b.get(k) == Some(&b'}') {
            k += 1;
            break;
        }
        let key = string(&mut k)?;
        expect(&mut k, b':')?;
        skip(&mut k);
        let value = match b.get(k) {
            Some(b'\'' | b'"') => Literal::Str(string(&mut k)?),
            Some(b'(') => {
                k += 1;
                let mut dims = Vec::new();
                loop {
                    skip(&mut k);
                    if b.get(k) == Some(&b')') {
                        k += 1;
                        break;
                    }
                    let from = k;
                    while k < b.len() && b[k].is_ascii_digit() {
                        k += 1;
                    }
                    let d = text[from..k]
                        .parse::<u64>()
                        .map_err(|_| format!("expected a dimension at byte {from}"))?;
                    dims.push(d);
                    skip(&mut k);
                    match b.get(k) {
                        Some(b',') => k += 1,
                        Some(b')') => {}
                        _ => return Err(format!("expected `,` or `)` at byte {k}")),
                    }
                }
                Literal::Tuple(dims)
            }
            _ if text[k..].starts_with("True") => {
                k += 4;
                Literal::Bool(true)
            }
            _ if text[k..].starts_with("False") => {
                k += 5;
                Literal::Bool(false)
            }
            _ => return Err(format!("unexpected value at byte {k}")),
        };
        if entries.iter().any(|(e, _)| *e == key) {
            return Err(format!("key '{key}' twice"));
        }
        entries.push((key, value));
        skip(&mut k);
        match b.get(k) {
            Some(b',') => k += 1,
            Some(b'}') => {}
            _ => return Err(format!("expected `,` or `}}` at byte {k}")),
        }
    }
    skip(&mut k);
    if k != b.len() {
        return Err(format!("text after the dictionary at byte {k}"));
    }
    let mut h = NpyHeader {
        descr: String::new(),
        fortran_order: false,
        shape: Vec::new(),
    };
    let mut seen = 0;
    for (key, value) in entries {
        match (key.as_str(), value) {
            ("descr", Literal::Str(s)) => h.descr = s,
            ("fortran_order", Literal::Bool(f)) => h.fortran_order = f,
            ("shape", Literal::Tuple(s)) => h.shape = s,
            (key @ ("descr" | "fortran_order" | "shape"), v) => {
                return Err(format!("'{key}' is {v:?}"))
            }
            (key, _) => return Err(format!("unexpected key '{key}'")),
        }
        seen += 1;
    }
    if seen != 3 {
        return Err("expected the keys 'descr', 'fortran_order' and 'shape'".into());
    }
    Ok(h)
}

/// Longest `.npy` header read (NumPy's are 128 bytes).
const MAX_HEADER: usize = 1 << 16;

/// Largest ratio of deflated to stored size (deflate's limit is 1032).
const MAX_DEFLATE_RATIO: u64 = 1100;

/// Longest central directory and end record read after the members.
const MAX_TRAILER: u64 = 1 << 20;

/// What [`read`] found of the members so far.
struct Found<V> {
    format: bool,
    shape: bool,
    indptr: Option<Vec<usize>>,
    indices: Option<Vec<u32>>,
    data: Option<Vec<V>>,
}

/// A message about `path`.
fn bad(path: &Path, msg: String) -> Error {
    Error::Parse {
        path: path.to_path_buf(),
        line: None,
        msg,
    }
}

/// An I/O error inside a member, explained.
fn member_io(path: &Path, member: &str, e: std::io::Error) -> Error {
    let why = match e.kind() {
        std::io::ErrorKind::UnexpectedEof => "the file ends inside it (truncated)".to_string(),
        std::io::ErrorKind::InvalidData => format!("{e} (the file is damaged)"),
        _ => return Error::io(path, e),
    };
    bad(path, format!("{member}: {why}"))
}

/// Reads `count` elements of `size` bytes each, converting each with `get` (which may
/// refuse it, with a message; its argument is the element's index).
fn read_elements<T>(
    r: &mut impl Read,
    count: usize,
    size: usize,
    mut get: impl FnMut(usize, &[u8]) -> std::result::Result<T, String>,
) -> std::result::Result<Vec<T>, std::result::Result<std::io::Error, String>> {
    let mut out = Vec::with_capacity(count);
    let mut buf = vec![0u8; CHUNK.min(count.max(1)) * size];
    let mut k = 0;
    while k < count {
        let m = (count - k).min(CHUNK);
        let chunk = &mut buf[..m * size];
        r.read_exact(chunk).map_err(Ok)?;
        for (a, e) in chunk.chunks_exact(size).enumerate() {
            out.push(get(k + a, e).map_err(Err)?);
        }
        k += m;
    }
    Ok(out)
}

/// Reads an `n x n` CSR matrix in SciPy's layout (see the [module docs](self)) from
/// `input`, a file of `bytes` bytes named `path` in messages. The whole input is read, so
/// that a hash taken around `input` covers the file. A shape other than `(n, n)` is a
/// [`Error::Mismatch`]; anything else wrong is an [`Error::Parse`] naming the member.
pub fn read<V: Value>(
    path: &Path,
    mut input: impl Read,
    bytes: u64,
    n: usize,
) -> Result<CsrArrays<V>> {
    let mut found = Found::<V> {
        format: false,
        shape: false,
        indptr: None,
        indices: None,
        data: None,
    };
    let mut members = 0u64;
    loop {
        let entry = zip::read::read_zipfile_from_stream(&mut input).map_err(|e| {
            let at = if members == 0 {
                "not a zip archive".to_string()
            } else {
                format!("after {members} members")
            };
            match e {
                zip::result::ZipError::Io(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => {
                    bad(path, format!("{at}: the file ends early (truncated)"))
                }
                e => bad(path, format!("{at}: {e}")),
            }
        })?;
        let Some(mut member) = entry else { break };
        members += 1;
        let name = member.name().to_string();
        let method = member.compression();
        let (size, packed) = (member.size(), member.compressed_size());
        let err = |msg: String| bad(path, format!("{name}: {msg}"));
        if !MEMBERS.contains(&name.as_str()) {
            return Err(bad(
                path,
                format!(
                    "unexpected member `{name}`: a SciPy CSR matrix holds {}",
                    MEMBERS.join(", ")
                ),
            ));
        }
        let bound = match method {
            CompressionMethod::Stored => packed,
            CompressionMethod::Deflated => packed.saturating_mul(MAX_DEFLATE_RATIO),
            m => return Err(err(format!("compressed with {m}: only stored or deflated"))),
        };
        if packed > bytes || size > bound {
            return Err(err(format!(
                "the zip header announces {size} bytes ({packed} compressed), more than a \
                 file of {bytes} bytes holds: truncated or damaged"
            )));
        }
        // The header.
        let mut magic = [0u8; 10];
        member
            .read_exact(&mut magic)
            .map_err(|e| member_io(path, &name, e))?;
        if &magic[..6] != b"\x93NUMPY" {
            return Err(err("not a .npy array (no \\x93NUMPY magic)".into()));
        }
        let (len, fixed) = match magic[6] {
            1 => (u16::from_le_bytes([magic[8], magic[9]]) as usize, 10),
            2 | 3 => {
                let mut more = [0u8; 2];
                member
                    .read_exact(&mut more)
                    .map_err(|e| member_io(path, &name, e))?;
                let l = u32::from_le_bytes([magic[8], magic[9], more[0], more[1]]) as usize;
                (l, 12)
            }
            v => {
                return Err(err(format!(
                    ".npy format version {v}.{}: unknown",
                    magic[7]
                )))
            }
        };
        if len > MAX_HEADER {
            return Err(err(format!(".npy header of {len} bytes: too long")));
        }
        let mut text = vec![0u8; len];
        member
            .read_exact(&mut text)
            .map_err(|e| member_io(path, &name, e))?;
        let text = String::from_utf8(text)
            .map_err(|_| err(".npy header is not text".into()))?
            .trim_end()
            .to_string();
        let h = parse_dict(&text).map_err(|e| err(format!(".npy header `{text}`: {e}")))?;
        if h.fortran_order {
            return Err(err("fortran_order True: expected False".into()));
        }
        let count = h
            .shape
            .iter()
            .try_fold(1u64, |a, &d| a.checked_mul(d))
            .ok_or_else(|| err(format!("shape {:?} overflows", h.shape)))?;
        let item: u64 = match h.descr.as_str() {
            "<i4" | "<f4" => 4,
            "<i8" | "<f8" => 8,
            "|S3" => 3,
            "<U3" => 12,
            _ => 0,
        };
        let want_shape = |want: &[u64]| -> Result<()> {
            if h.shape == want {
                Ok(())
            } else {
                Err(err(format!("shape {:?}, expected {want:?}", h.shape)))
            }
        };
        let want_descr = |want: &[&str]| -> Result<()> {
            if want.contains(&h.descr.as_str()) {
                Ok(())
            } else {
                Err(err(format!(
                    "dtype '{}', expected {}",
                    h.descr,
                    want.iter()
                        .map(|d| format!("'{d}'"))
                        .collect::<Vec<_>>()
                        .join(" or ")
                )))
            }
        };
        match name.as_str() {
            "format.npy" => want_descr(&["|S3", "<U3"])?,
            "shape.npy" => want_descr(&["<i8"])?,
            "indptr.npy" | "indices.npy" => want_descr(&["<i4", "<i8"])?,
            _ => want_descr(&[V::DESCR])?,
        }
        let body = count.saturating_mul(item);
        if fixed as u64 + len as u64 + body != size {
            return Err(err(format!(
                "the zip header gives {size} bytes; the .npy header describes {}",
                fixed as u64 + len as u64 + body
            )));
        }
        let count = count as usize;
        let item = item as usize;
        let io = |e: std::result::Result<std::io::Error, String>| match e {
            Ok(e) => member_io(path, &name, e),
            Err(msg) => err(msg),
        };
        let int = |e: &[u8]| -> i64 {
            if item == 4 {
                i32::from_le_bytes([e[0], e[1], e[2], e[3]]) as i64
            } else {
                i64::from_le_bytes([e[0], e[1], e[2], e[3], e[4], e[5], e[6], e[7]])
            }
        };
        let twice = || err("the member appears twice".into());
        match name.as_str() {
            "format.npy" => {
                want_shape(&[])?;
                let mut v = vec![0u8; item];
                member
                    .read_exact(&mut v)
                    .map_err(|e| member_io(path, &name, e))?;
                let s: String = if item == 3 {
                    String::from_utf8_lossy(&v).into_owned()
                } else {
                    v.chunks_exact(4)
                        .map(|c| {
                            char::from_u32(u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                                .unwrap_or('?')
                        })
                        .collect()
                };
                if s != "csr" {
                    return Err(err(format!(
                        "sparse format '{}', expected 'csr'",
                        s.trim_end_matches('\0')
                    )));
                }
                if std::mem::replace(&mut found.format, true) {
                    return Err(twice());
                }
            }
            "shape.npy" => {
                want_shape(&[2])?;
                let dims = read_elements(&mut member, 2, 8, |_, e| Ok(int(e))).map_err(io)?;
                if dims != [n as i64, n as i64] {
                    return Err(Error::Mismatch {
                        path: path.to_path_buf(),
                        msg: format!(
                            "matrix is {}x{}, the scene has {n} patches",
                            dims[0], dims[1]
                        ),
                    });
                }
                if std::mem::replace(&mut found.shape, true) {
                    return Err(twice());
                }
            }
            "indptr.npy" => {
                want_shape(&[n as u64 + 1])?;
                let mut prev = 0usize;
                let v = read_elements(&mut member, count, item, |k, e| {
                    let p = int(e);
                    if k == 0 && p != 0 {
                        return Err(format!("row pointer 0 is {p}, expected 0"));
                    }
                    match usize::try_from(p) {
                        Ok(p) if p >= prev => {
                            prev = p;
                            Ok(p)
                        }
                        _ => Err(format!(
                            "row pointer {k} is {p}, less than the one before ({prev})"
                        )),
                    }
                })
                .map_err(io)?;
                if found.indptr.replace(v).is_some() {
                    return Err(twice());
                }
            }
            "indices.npy" => {
                if h.shape.len() != 1 {
                    want_shape(&[count as u64])?;
                }
                let v = read_elements(&mut member, count, item, |k, e| {
                    let j = int(e);
                    if (0..n as i64).contains(&j) {
                        Ok(j as u32)
                    } else {
                        Err(format!("entry {k}: column {j}, outside 0..{n}"))
                    }
                })
                .map_err(io)?;
                if found.indices.replace(v).is_some() {
                    return Err(twice());
                }
            }
            _ => {
                if h.shape.len() != 1 {
                    want_shape(&[count as u64])?;
                }
                let v =
                    read_elements(&mut member, count, item, |_, e| Ok(V::get(e))).map_err(io)?;
                if found.data.replace(v).is_some() {
                    return Err(twice());
                }
            }
        }
        // The member's end: nothing more (its sizes matched), and its CRC-32 checked.
        let mut rest = [0u8; 1];
        match member.read(&mut rest) {
            Ok(0) => {}
            Ok(_) => return Err(err("bytes past the array".into())),
            Err(e) => return Err(member_io(path, &name, e)),
        }
    }
    // The central directory and its end record, which close every zip archive.
    let mut trailer = Vec::new();
    input
        .by_ref()
        .take(MAX_TRAILER)
        .read_to_end(&mut trailer)
        .map_err(|e| Error::io(path, e))?;
    let mut more = [0u8; 1];
    if input.read(&mut more).map_err(|e| Error::io(path, e))? != 0 {
        return Err(bad(
            path,
            format!("more than {MAX_TRAILER} bytes after the last member"),
        ));
    }
    let end = trailer.len().checked_sub(22).map(|k| &trailer[k..]);
    match end {
        Some(e) if e.starts_with(b"PK\x05\x06") => {
            let total = u16::from_le_bytes([e[10], e[11]]);
            if total != 0xffff && total as u64 != members {
                return Err(bad(
                    path,
                    format!("the zip directory lists {total} members, the archive holds {members}"),
                ));
            }
        }
        _ => {
            return Err(bad(
                path,
                "no end-of-central-directory record: the file is truncated or not a plain \
                 zip archive"
                    .into(),
            ))
        }
    }
    let missing: Vec<&str> = MEMBERS
        .iter()
        .zip([
            found.indices.is_some(),
            found.indptr.is_some(),
            found.format,
            found.shape,
            found.data.is_some(),
        ])
        .filter(|(_, has)| !has)
        .map(|(m, _)| *m)
        .collect();
    let (Some(indptr), Some(indices), Some(data), true, true) = (
        found.indptr,
        found.indices,
        found.data,
        found.format,
        found.shape,
    ) else {
        return Err(bad(
            path,
            format!(
                "no {}: not a SciPy sparse matrix (scipy.sparse.save_npz)",
                missing.join(", ")
            ),
        ));
    };
    let nnz = data.len();
    if indices.len() != nnz {
        return Err(bad(
            path,
            format!("indices.npy has {} entries, data.npy {nnz}", indices.len()),
        ));
    }
    if indptr[n] != nnz {
        return Err(bad(
            path,
            format!(
                "indptr.npy ends at {}, expected the entry count {nnz}",
                indptr[n]
            ),
        ));
    }
    for i in 0..n {
        let row = &indices[indptr[i]..indptr[i + 1]];
        if let Some(w) = row.windows(2).find(|w| w[0] >= w[1]) {
            return Err(bad(
                path,
                format!(
                    "indices.npy: row {i}: column {} after column {}: columns must increase \
                     within a row (each entry once)",
                    w[1], w[0]
                ),
            ));
        }
    }
    Ok(CsrArrays {
        indptr,
        indices,
        data,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Cursor;

    /// The 3 x 3 matrix `[[0, 0.5, 0.25], [0, 0, 0], [1, 0, 0]]`.
    const INDPTR: [usize; 4] = [0, 2, 2, 3];
    const INDICES: [u32; 3] = [1, 2, 0];
    const DATA: [f64; 3] = [0.5, 0.25, 1.0];

    /// A `.npy` array: `descr`, `shape`, then `body` as it is.
    fn npy(descr: &str, shape: &[usize], body: &[u8]) -> Vec<u8> {
        let mut v = npy_header(descr, shape);
        v.extend_from_slice(body);
        v
    }

    fn le<T: Copy, const K: usize>(xs: &[T], f: impl Fn(T) -> [u8; K]) -> Vec<u8> {
        xs.iter().flat_map(|&x| f(x)).collect()
    }

    /// The five members of the test matrix, as SciPy writes them, with `edit` applied.
    fn members(edit: impl FnOnce(&mut Vec<(String, Vec<u8>)>)) -> Vec<(String, Vec<u8>)> {
        let mut m = vec![
            (
                "indices.npy".to_string(),
                npy("<i4", &[3], &le(&[1i32, 2, 0], i32::to_le_bytes)),
            ),
            (
                "indptr.npy".to_string(),
                npy("<i4", &[4], &le(&[0i32, 2, 2, 3], i32::to_le_bytes)),
            ),
            ("format.npy".to_string(), npy("|S3", &[], b"csr")),
            (
                "shape.npy".to_string(),
                npy("<i8", &[2], &le(&[3i64, 3], i64::to_le_bytes)),
            ),
            (
                "data.npy".to_string(),
                npy("<f8", &[3], &le(&DATA, f64::to_le_bytes)),
            ),
        ];
        edit(&mut m);
        m
    }

    /// A zip archive of `members`.
    fn archive(members: &[(String, Vec<u8>)], method: CompressionMethod) -> Vec<u8> {
        let mut z = ZipWriter::new(Cursor::new(Vec::new()));
        for (name, bytes) in members {
            z.start_file(
                name.as_str(),
                SimpleFileOptions::default().compression_method(method),
            )
            .unwrap();
            z.write_all(bytes).unwrap();
        }
        z.finish().unwrap().into_inner()
    }

    fn parse<V: Value>(bytes: &[u8]) -> Result<CsrArrays<V>> {
        read(Path::new("F.npz"), bytes, bytes.len() as u64, 3)
    }

    fn temp(tag: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("radiosity-npz-{tag}-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn npy_headers_are_padded_to_64_bytes_and_parse_back() {
        for (descr, shape) in [("<f8", vec![3]), ("|S3", vec![]), ("<i8", vec![2, 5])] {
            let h = npy_header(descr, &shape);
            assert_eq!(h.len() % 64, 0);
            assert_eq!(*h.last().unwrap(), b'\n');
            let text = std::str::from_utf8(&h[10..]).unwrap().trim_end();
            let back = parse_dict(text).unwrap();
            assert_eq!(back.descr, descr);
            assert!(!back.fortran_order);
            assert_eq!(
                back.shape,
                shape.iter().map(|&d| d as u64).collect::<Vec<_>>()
            );
        }
        // NumPy's own spelling, and others it could write.
        let h = parse_dict("{'descr': '<i4', 'fortran_order': False, 'shape': (3,), }").unwrap();
        assert_eq!((h.descr.as_str(), h.shape.as_slice()), ("<i4", &[3u64][..]));
        assert!(parse_dict(r#"{"descr":"<f4","shape":(),"fortran_order":True}"#).is_ok());
        for bad in [
            "",
            "{'descr': '<f8', 'shape': (3,)}",
            "{'descr': '<f8', 'fortran_order': False, 'shape': (3,), 'x': 1}",
            "{'descr': '<f8', 'fortran_order': False, 'shape': (-3,)}",
            "{'descr': '<f8', 'fortran_order': False, 'shape': (3,) } x",
            "{'descr': '<f8', 'descr': '<f8', 'fortran_order': False, 'shape': (3,)}",
            "{'descr': 8, 'fortran_order': False, 'shape': (3,)}",
            "{'descr: '<f8'}",
        ] {
            assert!(parse_dict(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn scipys_own_files_are_read() {
        // `scipy.sparse.save_npz` (SciPy 1.17.1, NumPy 2.4.6) of the test matrix, with
        // compressed=False and with its default compressed=True.
        for bytes in [
            &include_bytes!("../tests/npz/scipy-stored.npz")[..],
            &include_bytes!("../tests/npz/scipy-deflated.npz")[..],
        ] {
            let m = parse::<f64>(bytes).unwrap();
            assert_eq!(m.indptr, INDPTR);
            assert_eq!(m.indices, INDICES);
            assert_eq!(m.data, DATA);
        }
    }

    #[test]
    fn written_files_read_back_and_have_scipys_members() {
        let dir = temp("roundtrip");
        // Rows of 0 to 4 entries, empty rows first and last.
        let n = 7;
        let indptr = [0, 0, 3, 4, 4, 8, 9, 9];
        let indices = [0, 4, 6, 2, 0, 1, 5, 6, 3];
        let data: Vec<f64> = (0..9).map(|k| k as f64 / 9.0 + 1e-17).collect();
        let se: Vec<f32> = (0..9).map(|k| (k as f32).sqrt() * 1e-3).collect();
        for compression in [Compression::Stored, Compression::Deflated] {
            let path = dir.join("F.npz");
            write(&path, n, &indptr, &indices, &data, compression).unwrap();
            let bytes = std::fs::read(&path).unwrap();
            let z = zip::ZipArchive::new(Cursor::new(&bytes)).unwrap();
            let names: Vec<&str> = z.file_names().collect();
            assert_eq!(names, MEMBERS);
            let m: CsrArrays<f64> = read(&path, &bytes[..], bytes.len() as u64, n).unwrap();
            assert_eq!(m.indptr, indptr);
            assert_eq!(m.indices, indices);
            assert_eq!(m.data, data);
            // Same arrays, same bytes.
            write(&path, n, &indptr, &indices, &data, compression).unwrap();
            assert_eq!(std::fs::read(&path).unwrap(), bytes);
            let path = dir.join("stderr.npz");
            write(&path, n, &indptr, &indices, &se, compression).unwrap();
            let bytes = std::fs::read(&path).unwrap();
            let m: CsrArrays<f32> = read(&path, &bytes[..], bytes.len() as u64, n).unwrap();
            assert_eq!(m.data, se);
            // float32 data is not read as float64.
            let e = read::<f64>(&path, &bytes[..], bytes.len() as u64, n)
                .unwrap_err()
                .to_string();
            assert!(e.contains("data.npy: dtype '<f4', expected '<f8'"), "{e}");
        }
        // An empty matrix.
        let path = dir.join("empty.npz");
        write::<f64>(&path, 2, &[0, 0, 0], &[], &[], Compression::Stored).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let m: CsrArrays<f64> = read(&path, &bytes[..], bytes.len() as u64, 2).unwrap();
        assert_eq!((m.indptr, m.data.len()), (vec![0, 0, 0], 0));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn malformed_archives_are_refused_naming_what_is_wrong() {
        let good = archive(&members(|_| {}), CompressionMethod::Stored);
        assert_eq!(parse::<f64>(&good).unwrap().data, DATA);
        let set = |name: &'static str, bytes: Vec<u8>| {
            move |m: &mut Vec<(String, Vec<u8>)>| {
                m.iter_mut().find(|(n, _)| n == name).unwrap().1 = bytes;
            }
        };
        type Edit = Box<dyn FnOnce(&mut Vec<(String, Vec<u8>)>)>;
        let cases: Vec<(Edit, &str)> = vec![
            (
                Box::new(set("data.npy", npy("<f4", &[3], &[0; 12]))),
                "data.npy: dtype '<f4', expected '<f8'",
            ),
            (
                Box::new(set("data.npy", npy(">f8", &[3], &[0; 24]))),
                "data.npy: dtype '>f8'",
            ),
            (
                Box::new(set("data.npy", npy("<f8", &[2], &[0; 16]))),
                "indices.npy has 3 entries, data.npy 2",
            ),
            (
                Box::new(set("data.npy", npy("<f8", &[3], &[0; 16]))),
                "data.npy: the zip header gives",
            ),
            (
                Box::new(set("data.npy", b"not an array".to_vec())),
                "data.npy: not a .npy array",
            ),
            (
                Box::new(set(
                    "shape.npy",
                    npy("<i8", &[2], &le(&[4i64, 4], i64::to_le_bytes)),
                )),
                "matrix is 4x4, the scene has 3 patches",
            ),
            (
                Box::new(set(
                    "shape.npy",
                    npy("<i4", &[2], &le(&[3i32, 3], i32::to_le_bytes)),
                )),
                "shape.npy: dtype '<i4', expected '<i8'",
            ),
            (
                Box::new(set("format.npy", npy("|S3", &[], b"csc"))),
                "format.npy: sparse format 'csc', expected 'csr'",
            ),
            (
                Box::new(set(
                    "format.npy",
                    npy(
                        "<U3",
                        &[],
                        &le(&['c', 's', 'r'], |c| (c as u32).to_le_bytes()),
                    ),
                )),
                "",
            ),
            (
                Box::new(set(
                    "indptr.npy",
                    npy("<i4", &[3], &le(&[0i32, 2, 3], i32::to_le_bytes)),
                )),
                "indptr.npy: shape [3], expected [4]",
            ),
            (
                Box::new(set(
                    "indptr.npy",
                    npy("<i4", &[4], &le(&[0i32, 2, 1, 3], i32::to_le_bytes)),
                )),
                "indptr.npy: row pointer 2 is 1, less than the one before (2)",
            ),
            (
                Box::new(set(
                    "indptr.npy",
                    npy("<i4", &[4], &le(&[1i32, 2, 2, 3], i32::to_le_bytes)),
                )),
                "indptr.npy: row pointer 0 is 1, expected 0",
            ),
            (
                Box::new(set(
                    "indptr.npy",
                    npy("<i8", &[4], &le(&[0i64, 2, 2, 2], i64::to_le_bytes)),
                )),
                "indptr.npy ends at 2, expected the entry count 3",
            ),
            (
                Box::new(set(
                    "indices.npy",
                    npy("<i4", &[3], &le(&[1i32, 3, 0], i32::to_le_bytes)),
                )),
                "indices.npy: entry 1: column 3, outside 0..3",
            ),
            (
                Box::new(set(
                    "indices.npy",
                    npy("<i8", &[3], &le(&[1i64, -1, 0], i64::to_le_bytes)),
                )),
                "indices.npy: entry 1: column -1, outside 0..3",
            ),
            (
                Box::new(set(
                    "indices.npy",
                    npy("<i4", &[3], &le(&[2i32, 1, 0], i32::to_le_bytes)),
                )),
                "row 0: column 1 after column 2: columns must increase",
            ),
            (
                Box::new(set(
                    "indices.npy",
                    npy("<i4", &[3], &le(&[1i32, 1, 0], i32::to_le_bytes)),
                )),
                "row 0: column 1 after column 1",
            ),
            (
                Box::new(set(
                    "indices.npy",
                    npy("<u4", &[3], &le(&[1u32, 2, 0], u32::to_le_bytes)),
                )),
                "indices.npy: dtype '<u4', expected '<i4' or '<i8'",
            ),
            (
                Box::new(|m: &mut Vec<(String, Vec<u8>)>| {
                    m.retain(|(n, _)| n != "shape.npy");
                }),
                "no shape.npy: not a SciPy sparse matrix",
            ),
            (
                Box::new(|m: &mut Vec<(String, Vec<u8>)>| {
                    m.push(("_is_array.npy".into(), npy("|b1", &[], &[1])));
                }),
                "unexpected member `_is_array.npy`",
            ),
            (
                Box::new(|m: &mut Vec<(String, Vec<u8>)>| {
                    let mut bytes = npy_header("<f8", &[3]);
                    bytes[20..26].copy_from_slice(b"'x': 1");
                    m[4].1 = bytes;
                }),
                "data.npy: .npy header",
            ),
        ];
        for (k, (edit, want)) in cases.into_iter().enumerate() {
            let bytes = archive(&members(edit), CompressionMethod::Stored);
            match parse::<f64>(&bytes) {
                // The `<U3` format string is SciPy's other spelling: accepted.
                Ok(_) if k == 8 => {}
                Ok(_) => panic!("case {k} accepted, expected {want}"),
                Err(e) => {
                    let e = e.to_string();
                    assert!(
                        k != 8 && e.starts_with("F.npz: ") && e.contains(want),
                        "case {k}: {e}"
                    );
                }
            }
        }
        // A member twice (the zip crate's writer refuses a name twice: the second
        // `data.npy` is renamed in place).
        let mut m = members(|_| {});
        m.push(("data.np_".into(), m[4].1.clone()));
        let mut bytes = archive(&m, CompressionMethod::Stored);
        while let Some(k) = bytes.windows(8).position(|w| w == b"data.np_") {
            bytes[k + 7] = b'y';
        }
        let e = parse::<f64>(&bytes).unwrap_err().to_string();
        assert!(e.contains("data.npy: the member appears twice"), "{e}");
        // Another compression.
        let e = parse::<f64>(&archive(&members(|_| {}), CompressionMethod::Deflated))
            .map(|_| ())
            .map_err(|e| e.to_string());
        assert_eq!(e, Ok(()));
        // Not a zip at all, and an empty file.
        for bytes in [&b"%%MatrixMarket matrix coordinate real general\n"[..], &[]] {
            let e = parse::<f64>(bytes).unwrap_err().to_string();
            assert!(e.contains("F.npz: not a zip archive"), "{e}");
        }
    }

    #[test]
    fn every_truncation_and_every_flipped_byte_is_handled() {
        for method in [CompressionMethod::Stored, CompressionMethod::Deflated] {
            let good = archive(&members(|_| {}), method);
            // Every proper prefix is refused (never a panic).
            for len in 0..good.len() {
                let e = parse::<f64>(&good[..len]);
                assert!(
                    e.is_err(),
                    "{method:?}: {len} of {} bytes accepted",
                    good.len()
                );
            }
            // A flipped bit anywhere: refused, or (in fields the reader does not use, such
            // as time stamps and the central directory's copies) the same matrix.
            let mut refused = 0;
            for k in 0..good.len() {
                let mut bytes = good.clone();
                bytes[k] ^= 0x10;
                match parse::<f64>(&bytes) {
                    Err(_) => refused += 1,
                    Ok(m) => {
                        assert_eq!((m.indptr, m.indices), (INDPTR.to_vec(), INDICES.to_vec()));
                        assert_eq!(m.data, DATA, "{method:?}: byte {k} flipped, wrong values");
                    }
                }
            }
            assert!(refused > good.len() / 3, "{method:?}: {refused} refused");
        }
        // A flipped bit in a stored array is caught by its CRC-32.
        let good = archive(&members(|_| {}), CompressionMethod::Stored);
        let at = good.len()
            - good
                .windows(8)
                .rev()
                .position(|w| w == 1.0f64.to_le_bytes())
                .unwrap()
            - 8;
        let mut bytes = good.clone();
        bytes[at] ^= 1;
        let e = parse::<f64>(&bytes).unwrap_err().to_string();
        assert!(e.contains("data.npy") && e.contains("damaged"), "{e}");
    }
}
