//! `radiosity suite run`: this program's answers to the suite, through the same path as any
//! other program's: one `factors` folder per case (`OUT/CASE/`: F.mtx, stderr.mtx,
//! patches.csv, provenance.json), computed from the exported OBJ files, for
//! `radiosity suite score --factors OUT`.

use std::path::Path;

use super::export::read_table;
use crate::error::{Error, Result};
use crate::mesh::Resolution;
use crate::pipeline::{self, EstimatorChoice, Quiet};
use crate::repair::Repair;
use crate::store;

/// How the factors are computed.
#[derive(Clone, Debug)]
pub struct Settings {
    /// Subdivision of each case's faces.
    pub resolution: Resolution,
    /// Estimator and its settings.
    pub estimator: EstimatorChoice,
    /// Seed of the random streams.
    pub seed: u64,
    /// Repair after estimation.
    pub repair: Repair,
}

/// One case computed.
#[derive(Clone, Debug)]
pub struct Done {
    /// Case name.
    pub case: String,
    /// Patches.
    pub patches: usize,
    /// Rays cast.
    pub rays: u64,
    /// Seconds of the form-factor stage.
    pub seconds: f64,
}

/// Computes a factors folder under `out` for every case of the suite exported in
/// `suite` (only those named in `only`, when it is not empty); `progress` is called after
/// each case.
pub fn run(
    suite: &Path,
    out: &Path,
    s: &Settings,
    only: &[String],
    progress: &mut dyn FnMut(&Done),
) -> Result<Vec<Done>> {
    let (table, base) = read_table(suite)?;
    for name in only {
        if !table.cases.iter().any(|c| &c.case == name) {
            return Err(Error::Config(format!("no case `{name}` in the suite")));
        }
    }
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let mut done = Vec::new();
    for c in &table.cases {
        if !only.is_empty() && !only.contains(&c.case) {
            continue;
        }
        let obj = base.join(&c.geometry);
        let summary = pipeline::factors_within(
            &obj.to_string_lossy(),
            s.resolution,
            &s.estimator,
            s.seed,
            &out.join(&c.case),
            s.repair,
            // The scorer reads Matrix Market, as it does every program's answers.
            store::Format::Mtx,
            None,
            false,
            &Quiet,
        )?;
        let d = Done {
            case: c.case.clone(),
            patches: summary.provenance.patches,
            rays: summary.provenance.rays,
            seconds: summary.provenance.seconds,
        };
        progress(&d);
        done.push(d);
    }
    Ok(done)
}
