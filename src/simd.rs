//! CPU feature dispatch for the sampling passes.
//!
//! The form-factor estimators make their samples in structure-of-arrays passes (unit-square
//! coordinates, points, directions, kernels, rays) that the compiler vectorizes. The crate
//! is built for baseline x86-64 (SSE2, 4 lanes of `f32`); [`with_widest`] runs a pass
//! compiled again for AVX2 (8 lanes) or for AVX-512 (the x86-64-v4 set: F, VL, BW, DQ; 16
//! lanes, one Embree packet) when the processor has it, as Embree itself picks its widest
//! kernels at run time.
//!
//! Results do not change: Rust never contracts a multiply and an add into a fused
//! multiply-add (even where the target features include FMA), so every lane computes the
//! same IEEE operations in the same order at any width (checked by the tests of the
//! callers, which compare the widths bit for bit).
//!
//! Also here, as the other processor-specific hint: [`prefetch`], for loops whose reads
//! are scattered by index.
#![allow(unsafe_code)]

use std::fmt;
use std::sync::atomic::{AtomicU8, Ordering};

/// Asks the processor to bring the cache line of `x` into its caches (`prefetcht0`), for a
/// read a loop will make a few steps later at an address no hardware prefetcher can guess
/// (a sparse row's columns). A hint: it reads nothing, cannot fault, and changes no
/// result; nothing on other processors.
#[inline(always)]
pub fn prefetch<T>(x: &T) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch reads no memory and cannot fault; `x` is a valid reference.
    unsafe {
        std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(
            (x as *const T).cast::<i8>(),
        )
    };
    #[cfg(not(target_arch = "x86_64"))]
    let _ = x;
}

/// A vector width the sampling passes can be compiled for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Width {
    /// The crate's baseline target (SSE2 on x86-64).
    Baseline = 0,
    /// AVX2.
    Avx2 = 1,
    /// AVX-512 F, VL, BW and DQ.
    Avx512 = 2,
}

impl Width {
    /// Every width, narrowest first.
    pub const ALL: [Width; 3] = [Width::Baseline, Width::Avx2, Width::Avx512];

    /// Whether this processor runs code compiled for this width.
    pub fn supported(self) -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::is_x86_feature_detected as has;
            match self {
                Width::Baseline => true,
                Width::Avx2 => has!("avx2"),
                Width::Avx512 => {
                    has!("avx512f") && has!("avx512vl") && has!("avx512bw") && has!("avx512dq")
                }
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            self == Width::Baseline
        }
    }

    /// The width named `s` (`baseline`, `avx2`, `avx512`).
    pub fn parse(s: &str) -> Option<Width> {
        Width::ALL.into_iter().find(|w| w.name() == s)
    }

    /// Lower-case name, as [`Width::parse`] reads it.
    pub fn name(self) -> &'static str {
        match self {
            Width::Baseline => "baseline",
            Width::Avx2 => "avx2",
            Width::Avx512 => "avx512",
        }
    }
}

impl fmt::Display for Width {
    fn fmt(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str(match self {
            Width::Baseline => "baseline",
            Width::Avx2 => "AVX2",
            Width::Avx512 => "AVX-512",
        })
    }
}

/// The widest width [`with_widest`] may use (all by default).
static LIMIT: AtomicU8 = AtomicU8::new(Width::Avx512 as u8);

/// Caps the width of the sampling passes process-wide (`radiosity bench --simd` measures
/// what each width gains; the tests compare them). Results are the same at every width.
pub fn set_limit(w: Width) {
    LIMIT.store(w as u8, Ordering::Relaxed);
}

/// The width [`with_widest`] runs at: the widest the processor supports, up to the limit
/// of [`set_limit`].
pub fn active() -> Width {
    let limit = LIMIT.load(Ordering::Relaxed);
    Width::ALL
        .into_iter()
        .rev()
        .find(|&w| w as u8 <= limit && w.supported())
        .unwrap_or(Width::Baseline)
}

/// Runs `f`, compiled for the width of [`active`]. The body of `f` must be inlined into it
/// to profit: callers pass an `#[inline(always)]` closure over `#[inline(always)]`
/// functions.
#[inline(always)]
pub fn with_widest<R>(f: impl FnOnce() -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    {
        match active() {
            // SAFETY: `active` returns a width only when the processor supports it, the
            // only requirement of calling a function compiled with its target features.
            Width::Avx512 => return unsafe { avx512(f) },
            Width::Avx2 => return unsafe { avx2(f) },
            Width::Baseline => {}
        }
    }
    f()
}

/// `f()` in a function compiled for AVX2, into which `f` is inlined.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn avx2<R>(f: impl FnOnce() -> R) -> R {
    f()
}

/// `f()` in a function compiled for AVX-512 (F, VL, BW, DQ), into which `f` is inlined.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,avx512f,avx512vl,avx512bw,avx512dq")]
unsafe fn avx512<R>(f: impl FnOnce() -> R) -> R {
    f()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_the_limit_caps_the_width() {
        for w in Width::ALL {
            assert_eq!(Width::parse(w.name()), Some(w));
        }
        assert_eq!(Width::parse("sse"), None);
        assert!(Width::Baseline.supported());
        set_limit(Width::Baseline);
        assert_eq!(active(), Width::Baseline);
        set_limit(Width::Avx512);
        assert!(active().supported());
    }
}
