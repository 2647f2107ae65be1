//! Reading input files without trusting them: regular files only (a FIFO would block, a
//! device such as `/dev/zero` never ends), a size cap, and encoding errors that name the
//! line.

use std::io::Read as _;
use std::path::Path;

use crate::error::{Error, Result};

/// Largest OBJ or MTL file read, in bytes.
pub const MAX_TEXT_BYTES: u64 = 1 << 30;

/// Opens `path` if it is a regular file (following links), with its length. Nothing is
/// opened otherwise, so a FIFO cannot block the run.
pub fn open_regular(path: &Path) -> Result<(std::fs::File, u64)> {
    let meta = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    if !meta.is_file() {
        return Err(Error::Parse {
            path: path.to_path_buf(),
            line: None,
            msg: "not a regular file (a FIFO, device or folder is not read)".into(),
        });
    }
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    Ok((file, meta.len()))
}

/// Reads a text input file of at most `cap` bytes (see [`decode`]).
pub fn read_text(path: &Path, cap: u64) -> Result<String> {
    let (file, len) = open_regular(path)?;
    let too_long = |len: u64| Error::Parse {
        path: path.to_path_buf(),
        line: None,
        msg: format!("{len} bytes, more than the {cap} an input file may have"),
    };
    if len > cap {
        return Err(too_long(len));
    }
    let mut bytes = Vec::with_capacity(len as usize);
    file.take(cap + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| Error::io(path, e))?;
    if bytes.len() as u64 > cap {
        return Err(too_long(bytes.len() as u64));
    }
    decode(path, bytes)
}

/// UTF-8 text from `bytes`. Comment lines (`#` first) may hold other encodings (a Latin-1
/// byte in an author's name): their invalid bytes become U+FFFD. Anywhere else an invalid
/// byte is refused with its line and column.
pub fn decode(path: &Path, bytes: Vec<u8>) -> Result<String> {
    let bytes = match String::from_utf8(bytes) {
        Ok(text) => return Ok(text),
        Err(e) => e.into_bytes(),
    };
    let mut text = String::with_capacity(bytes.len());
    for (k, line) in bytes.split_inclusive(|&b| b == b'\n').enumerate() {
        match std::str::from_utf8(line) {
            Ok(t) => text.push_str(t),
            Err(e) if line.trim_ascii_start().starts_with(b"#") => {
                let _ = e;
                text.push_str(&String::from_utf8_lossy(line));
            }
            Err(e) => {
                let col = e.valid_up_to();
                return Err(Error::Parse {
                    path: path.to_path_buf(),
                    line: Some(k + 1),
                    msg: format!(
                        "byte 0x{:02x} at column {} is not UTF-8 (only comments may use \
                         another encoding)",
                        line[col],
                        col + 1
                    ),
                });
            }
        }
    }
    Ok(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn latin1_is_accepted_in_comments_and_refused_elsewhere_with_its_line() {
        let p = Path::new("s.obj");
        let ok = decode(p, b"# caf\xe9\nv 0 0 0\n".to_vec()).unwrap();
        assert_eq!(ok, "# caf\u{fffd}\nv 0 0 0\n");
        let e = decode(p, b"v 0 0 0\nusemtl caf\xe9\n".to_vec())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("s.obj:2") && e.contains("0xe9") && e.contains("column 11"),
            "{e}"
        );
    }

    #[test]
    fn special_files_are_refused_without_blocking() {
        for dev in ["/dev/zero", "/dev/null", "/tmp"] {
            if Path::new(dev).exists() {
                let e = read_text(Path::new(dev), MAX_TEXT_BYTES)
                    .unwrap_err()
                    .to_string();
                assert!(e.contains(dev) && e.contains("not a regular file"), "{e}");
            }
        }
    }

    #[test]
    fn a_file_over_the_cap_is_refused() {
        let dir = std::env::temp_dir().join(format!("radiosity-input-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("big.obj");
        std::fs::write(&path, "v 0 0 0\n".repeat(10)).unwrap();
        let e = read_text(&path, 16).unwrap_err().to_string();
        assert!(e.contains("80 bytes"), "{e}");
        assert_eq!(read_text(&path, 80).unwrap().len(), 80);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
