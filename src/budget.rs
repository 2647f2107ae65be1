//! The memory a run will need, estimated before any expensive work and checked against what
//! the machine has: a run that cannot fit is refused at once with the number and the
//! setting that would fit, instead of aborting in the allocator minutes later.
//!
//! The estimate ([`Estimate`]) is an upper bound made of
//! - the patches: mesh arrays, the Embree scene, per-vertex output and solver vectors
//!   ([`PER_PATCH`] bytes each, rounded up from the arrays' sizes);
//! - the form factors: [`PER_ENTRY`] bytes per stored entry (the 16 of the stored matrix,
//!   plus half of a row entry's 24: estimators that compute the upper triangle hold it
//!   while the whole matrix is assembled), at most
//!   `n - 1` entries per row, fewer for the estimators that cast a fixed number of rays per
//!   row (hemisphere, hemicube); a dense `n x n` copy for the direct solver (the
//!   diagnostics' copies of back entries, at most 16 bytes times
//!   [`crate::matrix::RECIPROCITY_SAMPLE`], come after the row entries are freed, and
//!   fit in their place);
//! - the preview: [`PER_PIXEL`] bytes per output pixel (2 x 2 samples of colour and depth,
//!   the 8-bit image and its encoding).
//!
//! The limit is `--max-memory` when given, else `MemAvailable` of `/proc/meminfo` (no check
//! when neither is known).

use crate::error::{Error, Result};

/// Bytes per patch besides the form factors (an upper bound, see the module docs).
pub const PER_PATCH: u64 = 1024;

/// Bytes per stored form factor at the peak of assembly: the stored matrix's column, value
/// and standard error, and the upper triangle's row entries held while it is mirrored.
pub const PER_ENTRY: u64 = (crate::matrix::FormFactors::BYTES_PER_ENTRY
    + std::mem::size_of::<crate::matrix::Entry>() / 2) as u64;

/// Bytes per preview pixel.
pub const PER_PIXEL: u64 = 96;

/// Most patches a run accepts, whatever the memory.
pub const MAX_PATCHES: usize = 100_000_000;

/// What a run will hold at its peak, in bytes, by part.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Estimate {
    /// Patches expected.
    pub patches: usize,
    /// Mesh, visibility, solver vectors, per-vertex output.
    pub mesh: u64,
    /// Form factors (sparse, and dense for the direct solver).
    pub matrix: u64,
    /// Preview buffers.
    pub preview: u64,
}

impl Estimate {
    /// The estimate for `patches` patches, at most `per_row` stored entries per row,
    /// `dense` when the solver holds an `n x n` copy, and `pixels` preview pixels.
    pub fn new(patches: usize, per_row: usize, dense: bool, pixels: u64) -> Estimate {
        let n = patches as u64;
        let per_row = (per_row as u64).min(n.saturating_sub(1));
        let dense = if dense {
            n.saturating_mul(n).saturating_mul(8)
        } else {
            0
        };
        Estimate {
            patches,
            mesh: n.saturating_mul(PER_PATCH),
            matrix: n
                .saturating_mul(per_row)
                .saturating_mul(PER_ENTRY)
                .saturating_add(dense),
            preview: pixels.saturating_mul(PER_PIXEL),
        }
    }

    /// The whole estimate.
    pub fn total(&self) -> u64 {
        self.mesh
            .saturating_add(self.matrix)
            .saturating_add(self.preview)
    }
}

/// `MemAvailable` of `/proc/meminfo`, in bytes, when the system says.
pub fn available() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb.saturating_mul(1024))
}

/// The memory a run may use and where that figure comes from: `--max-memory` when given,
/// else the available memory; `None` when neither is known (no check then).
pub fn limit_of(max_memory: Option<u64>) -> Option<(u64, &'static str)> {
    match max_memory {
        Some(l) => Some((l, "--max-memory")),
        None => available().map(|a| (a, "available (MemAvailable in /proc/meminfo)")),
    }
}

/// Bytes as GiB with two decimals.
pub fn gib(bytes: u64) -> String {
    format!("{:.2} GiB", bytes as f64 / (1u64 << 30) as f64)
}

/// Bytes as GiB with two decimals, or MiB below 1 GiB.
pub fn size(bytes: u64) -> String {
    if bytes < 1 << 30 {
        format!("{:.1} MiB", bytes as f64 / (1u64 << 20) as f64)
    } else {
        gib(bytes)
    }
}

/// Parses a memory size: bytes, or with a `K`, `M`, `G` or `T` suffix (powers of 1024).
pub fn parse_bytes(s: &str) -> std::result::Result<u64, String> {
    let t = s.trim();
    let (num, shift) = match t.char_indices().last() {
        Some((k, c)) if c.is_ascii_alphabetic() => {
            let shift = match c.to_ascii_uppercase() {
                'K' => 10,
                'M' => 20,
                'G' => 30,
                'T' => 40,
                _ => {
                    return Err(format!(
                        "`{s}`: expected a size such as 4G, 512M or 1000000"
                    ))
                }
            };
            (&t[..k], shift)
        }
        _ => (t, 0),
    };
    let x: f64 = num
        .trim()
        .parse()
        .map_err(|_| format!("`{s}`: expected a size such as 4G, 512M or 1000000"))?;
    let bytes = x * (1u64 << shift) as f64;
    if !(bytes >= 1.0 && bytes < u64::MAX as f64) {
        return Err(format!("`{s}`: expected a size of at least one byte"));
    }
    Ok(bytes as u64)
}

/// Refuses `est` when it exceeds `limit` (`--max-memory`) or, without one, the available
/// memory. `fit(p)` is the estimate the same run would have with `p` patches, to name the
/// patch count that would fit.
pub fn check(est: &Estimate, limit: Option<u64>, fit: impl Fn(usize) -> Estimate) -> Result<()> {
    if est.patches > MAX_PATCHES {
        return Err(Error::Config(format!(
            "about {} patches, more than the {MAX_PATCHES} a run accepts (use fewer --patches \
             or a longer --max-edge)",
            est.patches
        )));
    }
    let Some((limit, source)) = limit_of(limit) else {
        return Ok(());
    };
    if est.total() <= limit {
        return Ok(());
    }
    // The largest patch count that fits, by bisection (the estimate grows with the count).
    let (mut lo, mut hi) = (0usize, est.patches);
    while lo + 1 < hi {
        let mid = lo + (hi - lo) / 2;
        if fit(mid).total() <= limit {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let advice = if lo == 0 {
        "the preview alone does not fit: use a smaller --size".to_string()
    } else if est.preview > limit / 2 {
        format!("use a smaller --size, or --patches {lo} or fewer")
    } else {
        format!("use --patches {lo} or fewer (or a longer --max-edge)")
    };
    Err(Error::Config(format!(
        "this run needs up to {} ({} patches: mesh and solve {}, form factors {}, preview {}), \
         more than the {} {source}; {advice}, or set --max-memory if the estimate is too \
         pessimistic",
        gib(est.total()),
        est.patches,
        gib(est.mesh),
        gib(est.matrix),
        gib(est.preview),
        gib(limit)
    )))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse() {
        assert_eq!(parse_bytes("1000").unwrap(), 1000);
        assert_eq!(parse_bytes("4G").unwrap(), 4 << 30);
        assert_eq!(parse_bytes("1.5k").unwrap(), 1536);
        assert!(parse_bytes("0").is_err() && parse_bytes("lots").is_err());
        assert!(parse_bytes("1e30T").is_err());
    }

    #[test]
    fn a_run_past_the_limit_is_refused_with_what_fits() {
        let fit = |p: usize| Estimate::new(p, p, false, 512 * 512);
        let est = fit(50_000_000);
        let e = check(&est, Some(4 << 30), fit).unwrap_err().to_string();
        assert!(
            e.contains("50000000 patches") && e.contains("--max-memory"),
            "{e}"
        );
        // The count it names fits, one more does not.
        let k: usize = e
            .split("--patches ")
            .nth(1)
            .and_then(|t| t.split(' ').next())
            .and_then(|t| t.parse().ok())
            .unwrap_or_else(|| panic!("{e}"));
        assert!(
            fit(k).total() <= 4 << 30 && fit(k + 1).total() > 4 << 30,
            "{k}"
        );
        assert!(check(&fit(1000), Some(4 << 30), fit).is_ok());
        let e = check(&fit(usize::MAX), None, fit).unwrap_err().to_string();
        assert!(e.contains("more than the 100000000"), "{e}");
        let huge_preview = |p: usize| Estimate::new(p, p, false, 8192 * 8192);
        let e = check(&huge_preview(1000), Some(1 << 30), huge_preview)
            .unwrap_err()
            .to_string();
        assert!(e.contains("--size"), "{e}");
    }
}
