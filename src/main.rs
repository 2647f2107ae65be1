//! The `radiosity` command line: parses arguments, runs, prints the error chain.

mod cli;

use std::process::ExitCode;

/// mimalloc keeps freed pages in per-thread heaps: the row buffers and matrix arrays of a
/// stage are not handed back to the kernel and faulted in again (glibc's allocator did
/// that, 2 to 8% of the form-factor stage, `docs/PERFORMANCE.md`).
#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> ExitCode {
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
