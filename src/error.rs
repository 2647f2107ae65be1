//! The crate's error type. Every variant carries what a user needs to fix the problem:
//! the file and line, the material or patch, or the Embree message.
//!
//! Grouped by what the user can do about it: fix the input (`Io`, `Parse`, `Material`,
//! `Scene`, `UnknownScene`, `Mismatch`), change the settings (`Config`, `NotConverged`, `Singular`),
//! or report a bug / a broken install (`Embree`, `Output`).

use std::path::PathBuf;

/// Everything that can go wrong in the library.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file could not be read or written.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The system's reason.
        #[source]
        source: std::io::Error,
    },
    /// A malformed line in an input file.
    #[error("{}{}: {msg}", path.display(), line.map(|l| format!(":{l}")).unwrap_or_default())]
    Parse {
        /// The file.
        path: PathBuf,
        /// 1-based line number, when known.
        line: Option<usize>,
        /// What is wrong.
        msg: String,
    },
    /// A material with values outside their physical range.
    #[error("{}{}: material `{material}`: {msg}", path.display(), line.map(|l| format!(":{l}")).unwrap_or_default())]
    Material {
        /// The MTL (or OBJ) file.
        path: PathBuf,
        /// 1-based line number, when known.
        line: Option<usize>,
        /// The material name.
        material: String,
        /// What is wrong.
        msg: String,
    },
    /// A scene that cannot be solved as given (no emitter, nothing left after cleaning...).
    #[error("scene `{scene}`: {msg}")]
    Scene {
        /// Scene name (file or built-in name).
        scene: String,
        /// What is wrong.
        msg: String,
    },
    /// A built-in scene name that does not exist.
    #[error("no built-in scene `{name}` and no such file (built-in scenes: {known})")]
    UnknownScene {
        /// The name asked for.
        name: String,
        /// The names that exist.
        known: String,
    },
    /// Settings that cannot work together.
    #[error("invalid settings: {0}")]
    Config(String),
    /// A stored matrix or result that does not belong to the scene it is used with.
    #[error("{}: {msg}", path.display())]
    Mismatch {
        /// The stored file.
        path: PathBuf,
        /// What differs.
        msg: String,
    },
    /// An iterative solver stopped before reaching its tolerance.
    #[error("{solver} did not converge: relative residual {residual:.3e} after {iterations} iterations (tolerance {tolerance:.1e}){hint}")]
    NotConverged {
        /// The solver's name.
        solver: String,
        /// Iterations done.
        iterations: usize,
        /// Final relative residual.
        residual: f64,
        /// The tolerance asked for.
        tolerance: f64,
        /// A suggestion, starting with "; ".
        hint: String,
    },
    /// The radiosity system has no physical solution the solver can return: singular or
    /// nearly so (a closed scene with `rho -> 1`), or a form-factor matrix whose rows sum so
    /// far above 1 that `diag(rho) F` has spectral radius 1 or more.
    #[error("{solver}: the radiosity system is singular or unphysical: {msg}")]
    Singular {
        /// The solver's name.
        solver: String,
        /// What was found and what to do about it.
        msg: String,
    },
    /// Embree reported an error.
    #[error("Embree: {0}")]
    Embree(String),
    /// An output file could not be produced.
    #[error("{}: {msg}", path.display())]
    Output {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        msg: String,
    },
    /// A run of several processes ([`crate::cluster`]) failed on one of them, or between
    /// them.
    #[error("rank {rank} of {size}: {msg}")]
    Cluster {
        /// The rank that failed.
        rank: usize,
        /// How many ranks the run has.
        size: usize,
        /// What went wrong.
        msg: String,
    },
}

/// The crate's result type.
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    /// An I/O error on `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }
}
