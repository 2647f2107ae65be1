//! The leaderboard: several programs' scores side by side, as Markdown tables and a chart of
//! relative error against time, one series per program (`radiosity suite board`).
//!
//! The chart has one point per answered case with a time: its seconds and its relative
//! error, both on log axes. An error of exactly 0 cannot be drawn on a log axis and is
//! drawn at 1e-16 (about the rounding of an `f64` factor); the tables give every value.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::score::Score;
use super::Class;
use crate::error::{Error, Result};
use crate::output::chart::{scatter_chart, Series};
use crate::output::write_atomic;

/// Smallest relative error drawn.
pub const FLOOR: f64 = 1e-16;

fn e(x: Option<f64>) -> String {
    x.map(|x| format!("{x:.1e}")).unwrap_or_else(|| "–".into())
}

/// The Markdown tables: one row per program (overall), then the median relative error per
/// class and program.
pub fn tables(scores: &[Score]) -> String {
    let mut t = String::new();
    let _ = writeln!(
        t,
        "| program | answered | median rel. error | worst rel. error (case) | flagged | bars: given / within 2 bars | time, s (sum) |"
    );
    let _ = writeln!(t, "|---|---|---|---|---|---|---|");
    for s in scores {
        let o = s.overall();
        let _ = writeln!(
            t,
            "| {} | {} / {} | {} | {} ({}) | {} | {} / {} | {} |",
            s.tool,
            o.answered,
            o.cases,
            e(o.median_relative),
            e(o.worst_relative),
            o.worst_case.as_deref().unwrap_or("–"),
            o.flagged,
            o.with_bar,
            o.within_2_bars
                .map(|x| format!("{:.0}%", 100.0 * x))
                .unwrap_or_else(|| "–".into()),
            o.seconds
                .map(|x| format!("{x:.3}"))
                .unwrap_or_else(|| "–".into()),
        );
    }
    let _ = writeln!(t, "\nMedian (worst) relative error per class:\n");
    let _ = write!(t, "| class |");
    for s in scores {
        let _ = write!(t, " {} |", s.tool);
    }
    let _ = write!(t, "\n|---|");
    for _ in scores {
        let _ = write!(t, "---|");
    }
    let _ = writeln!(t);
    for class in Class::ALL {
        let _ = write!(t, "| {} |", class.name());
        for s in scores {
            let c = s.classes.iter().find(|c| c.class == class.name());
            let _ = write!(
                t,
                " {} |",
                c.map(|c| format!("{} ({})", e(c.median_relative), e(c.worst_relative)))
                    .unwrap_or_else(|| "–".into())
            );
        }
        let _ = writeln!(t);
    }
    let _ = writeln!(t, "\nCommands:\n");
    for s in scores {
        let _ = writeln!(t, "- {}: `{}`", s.tool, s.command);
    }
    t
}

/// Writes `base.md` (the tables) and the chart `base.svg`, `base.png`; returns the paths.
pub fn write(base: &Path, scores: &[Score]) -> Result<Vec<PathBuf>> {
    if scores.is_empty() {
        return Err(Error::Config("no scores to put on the board".into()));
    }
    if let Some(s) = scores.iter().find(|s| s.suite != scores[0].suite) {
        return Err(Error::Config(format!(
            "scores of different suites: `{}` is on {}, `{}` on {}",
            scores[0].tool, scores[0].suite, s.tool, s.suite
        )));
    }
    let md = base.with_extension("md");
    let text = tables(scores);
    write_atomic(&md, |tmp| {
        std::fs::write(tmp, &text).map_err(|e| Error::io(tmp, e))
    })?;
    let series: Vec<Series> = scores
        .iter()
        .map(|s| {
            let pts = s
                .cases
                .iter()
                .filter_map(|c| match (c.seconds, c.relative) {
                    (Some(t), Some(r)) if t > 0.0 => Some((t, r.max(FLOOR))),
                    _ => None,
                })
                .collect();
            Series::new(s.tool.clone(), pts)
        })
        .collect();
    let mut out = vec![md];
    out.extend(scatter_chart(
        base,
        &format!(
            "{}: relative error against time, one point per case",
            scores[0].suite
        ),
        "seconds per case",
        "relative error |F - exact| / exact",
        true,
        true,
        &series,
    )?);
    Ok(out)
}
