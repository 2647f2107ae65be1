//! The `radiosity` command line: parses arguments, runs, prints the error chain.

mod cli;

use std::process::ExitCode;

/// mimalloc keeps freed pages in per-thread heaps for reuse, where glibc's allocator
/// handed the row buffers of the form-factor stage back to the kernel and faulted them in
/// again: the stage runs 3 to 9% faster (`docs/PERFORMANCE.md`, section 2).
#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> ExitCode {
    match cli::run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            cli::print_error(&e, "");
            ExitCode::FAILURE
        }
    }
}
