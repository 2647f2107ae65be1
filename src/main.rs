//! The `radiosity` command line: parses arguments, runs, prints the error chain.

mod cli;

use std::process::ExitCode;

/// mimalloc keeps freed pages in per-thread heaps: the row buffers and matrix arrays of a
/// stage are not handed back to the kernel and faulted in again (glibc's allocator did
/// that, 2 to 8% of the form-factor stage, `docs/PERFORMANCE.md`).
#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// `mi_option_purge_delay` in `mimalloc.h` (the same position in mimalloc 2 and 3).
const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

/// Freed memory stays with the process for 10 s before mimalloc returns it to the kernel
/// (jemalloc's default decay; mimalloc's own is 10 ms in version 2 and 1 s in version 3),
/// so that a stage, or the next run of one in `radiosity bench`, reuses what the one before
/// freed instead of taking fresh pages that the kernel must zero a fault at a time: in
/// back-to-back runs of the 32 x 32 cube's form factors, zeroing fresh pages was a fifth of
/// the profile. Peak memory is unchanged. Left alone when `MIMALLOC_PURGE_DELAY` is set,
/// or when the option does not hold one of those defaults (a mimalloc that numbers its
/// options differently).
#[allow(unsafe_code)]
fn keep_freed_memory() {
    if std::env::var_os("MIMALLOC_PURGE_DELAY").is_some() {
        return;
    }
    // SAFETY: mi_option_get / mi_option_set read and write one of mimalloc's option
    // values; an option index within its enum is all they require.
    unsafe {
        let default = libmimalloc_sys::mi_option_get(MI_OPTION_PURGE_DELAY);
        if default == 10 || default == 1000 {
            libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, 10_000);
        }
    }
}

fn main() -> ExitCode {
    keep_freed_memory();
    match cli::run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            let mut source = e.source();
            while let Some(s) = source {
                eprintln!("  caused by: {s}");
                source = s.source();
            }
            ExitCode::FAILURE
        }
    }
}
