//! CPU feature dispatch for the sampling passes.
//!
//! The form-factor estimators make their samples in structure-of-arrays passes (unit-square
//! coordinates, points, directions, kernels, rays) that the compiler vectorizes. The crate
//! is built for baseline x86-64 (SSE2, 4 lanes of `f32`); [`with_avx2`] runs a pass compiled
//! again with AVX2 enabled (8 lanes) when the processor has it, as Embree itself picks its
//! widest kernels at run time.
//!
//! Results do not change: Rust never contracts a multiply and an add into a fused
//! multiply-add, and `fma` is not enabled here, so every lane computes the same IEEE
//! operations in the same order at either width (checked by the tests of the callers,
//! which compare both paths bit for bit).
#![allow(unsafe_code)]

use std::sync::atomic::{AtomicBool, Ordering};

/// Whether [`with_avx2`] may use AVX2 (on by default).
static ENABLED: AtomicBool = AtomicBool::new(true);

/// Allows or forbids the AVX2 passes process-wide (`radiosity bench --no-simd` measures
/// what they gain; the tests compare both widths). Results are the same either way.
pub fn set_enabled(on: bool) {
    ENABLED.store(on, Ordering::Relaxed);
}

/// True when [`with_avx2`] runs its AVX2 version: allowed, and supported by the processor.
pub fn avx2_active() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        ENABLED.load(Ordering::Relaxed) && std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Runs `f`, compiled with AVX2 enabled when the processor supports it (x86-64 only) and
/// [`set_enabled`] has not turned it off. The body of `f` must be inlined into it to
/// profit: callers pass an `#[inline(always)]` closure over `#[inline(always)]` functions.
#[inline(always)]
pub fn with_avx2<R>(f: impl FnOnce() -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    {
        if avx2_active() {
            // SAFETY: the processor supports AVX2 (checked just above), the only
            // requirement of calling a function compiled with that target feature.
            return unsafe { avx2(f) };
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
