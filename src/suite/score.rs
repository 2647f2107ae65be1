//! `radiosity suite score`: a program's answers against the exact values, per case and per
//! difficulty class.
//!
//! Answers come in one of three forms:
//! - **a folder per case** (`DIR/CASE/`), holding a patch-to-patch matrix `F.mtx` (Matrix
//!   Market, `coordinate` or `array`, `real`, `general`; entries in any order), optionally
//!   `stderr.mtx` (the standard error of each entry, same form), a patch table
//!   `patches.csv` and optionally `provenance.json` (its `seconds` is the time). The patch
//!   table has a header; row `k` (or the row whose `id` is `k`) describes patch `k` by its
//!   `area` and the surface it belongs to: a `surface` column (surface name), a `material`
//!   column (the suite gives every surface a material of its own name) or a `face` column
//!   (0-based OBJ face index). A factors folder of this program (`radiosity factors`) is
//!   such a folder.
//! - **a CSV** of surface-to-surface factors, with a header:
//!   `case,from,to,value[,stderr][,seconds]`.
//!
//! A folder's patch matrix is aggregated to the surfaces by area weighting,
//! `F_AB = Σ_{i∈A} A_i Σ_{j∈B} F_ij / Σ_{i∈A} A_i` (the emitter-splitting and
//! receiver-additivity rules), and its standard error, taking the entries as independent
//! (this program's streams are keyed on the pair), as
//! `sqrt(Σ_{i∈A} (A_i / A_A)² Σ_{j∈B} se_ij²)`.
//!
//! Per case the score has the error `value - exact`, the relative error, the error over the
//! program's own bar where it gives one, and the time where it gives one. A case is
//! **flagged** when its relative error exceeds the tolerance (`--tolerance`) and, where the
//! program gives a bar, its error also exceeds `--sigmas` bars: a program is only held to
//! the accuracy it claims, down to the tolerance. The summary per class has the median and
//! worst relative error and the coverage of the bars (the share of cases with a bar whose
//! error is within 2 bars; about 95% for honest standard errors).

use std::collections::{BTreeMap, HashMap};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::export::{csv_field, Table, TableCase};
use super::{Class, VERSION};
use crate::error::{Error, Result};
use crate::input::{read_text, MAX_TEXT_BYTES};
use crate::output::write_atomic;

/// One answer: a surface-to-surface factor of a case.
#[derive(Clone, Debug, PartialEq)]
pub struct Answer {
    /// Case name.
    pub case: String,
    /// From-surface.
    pub from: String,
    /// To-surface.
    pub to: String,
    /// The program's value.
    pub value: f64,
    /// Its standard error, if the program gives one.
    pub stderr: Option<f64>,
    /// Seconds the program took for the case, if given.
    pub seconds: Option<f64>,
}

/// When a case is flagged (see the [module docs](self)).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Rule {
    /// Relative error above which a case may be flagged.
    pub tolerance: f64,
    /// Bars a flagged case's error must also exceed, where the program gives one.
    pub sigmas: f64,
}

impl Default for Rule {
    fn default() -> Rule {
        Rule {
            tolerance: 1e-3,
            sigmas: 3.0,
        }
    }
}

/// The score of one case.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CaseScore {
    /// Case name.
    pub case: String,
    /// Difficulty class.
    pub class: String,
    /// Exact value.
    pub exact: f64,
    /// The program's value (absent: not answered).
    pub value: Option<f64>,
    /// `value - exact`.
    pub error: Option<f64>,
    /// `|value - exact| / exact`.
    pub relative: Option<f64>,
    /// The program's standard error.
    pub stderr: Option<f64>,
    /// `|error| / stderr`.
    pub sigmas: Option<f64>,
    /// Seconds, if given.
    pub seconds: Option<f64>,
    /// Flagged by the [`Rule`].
    pub flagged: bool,
}

/// Summary of a set of cases (one class, or all).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    /// Class name, or `all`.
    pub class: String,
    /// Cases in the suite.
    pub cases: usize,
    /// Cases answered.
    pub answered: usize,
    /// Median relative error of the answered cases.
    pub median_relative: Option<f64>,
    /// Worst relative error.
    pub worst_relative: Option<f64>,
    /// The case with the worst relative error.
    pub worst_case: Option<String>,
    /// Answered cases with a bar.
    pub with_bar: usize,
    /// Of those, the share whose error is within 2 bars.
    pub within_2_bars: Option<f64>,
    /// Flagged cases.
    pub flagged: usize,
    /// Sum of the seconds given.
    pub seconds: Option<f64>,
}

/// A program's score on the suite.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Score {
    /// Suite version scored against.
    pub suite: String,
    /// The program (and settings) scored.
    pub tool: String,
    /// The command that made the answers, if given.
    pub command: String,
    /// The flagging rule.
    pub rule: Rule,
    /// Per case, in table order.
    pub cases: Vec<CaseScore>,
    /// Per class, in [`Class::ALL`] order, then `all`.
    pub classes: Vec<Summary>,
}

impl Score {
    /// The summary over all cases.
    pub fn overall(&self) -> &Summary {
        self.classes.last().expect("a score has an overall summary")
    }

    /// Names of the flagged cases.
    pub fn flagged(&self) -> Vec<&str> {
        self.cases
            .iter()
            .filter(|c| c.flagged)
            .map(|c| c.case.as_str())
            .collect()
    }
}

fn parse_err(path: &Path, line: usize, msg: impl Into<String>) -> Error {
    Error::Parse {
        path: path.to_path_buf(),
        line: Some(line),
        msg: msg.into(),
    }
}

/// Splits a CSV line (fields may be double-quoted, with `""` for a quote).
fn split_csv(line: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut cur = String::new();
    let mut quoted = false;
    let mut chars = line.chars().peekable();
    while let Some(c) = chars.next() {
        match c {
            '"' if quoted && chars.peek() == Some(&'"') => {
                cur.push('"');
                chars.next();
            }
            '"' => quoted = !quoted,
            ',' if !quoted => out.push(std::mem::take(&mut cur)),
            _ => cur.push(c),
        }
    }
    out.push(cur);
    out.into_iter().map(|s| s.trim().to_string()).collect()
}

/// A finite number from a field.
fn number(path: &Path, line: usize, what: &str, s: &str) -> Result<f64> {
    let x: f64 = s
        .parse()
        .map_err(|_| parse_err(path, line, format!("{what} `{s}` is not a number")))?;
    if !x.is_finite() {
        return Err(parse_err(path, line, format!("{what} is {x}, not finite")));
    }
    Ok(x)
}

/// Reads a CSV of answers `case,from,to,value[,stderr][,seconds]` (header required; `#`
/// lines are comments). Each case of `table` may be answered once, with its from and to
/// surfaces.
pub fn read_csv(path: &Path, table: &Table) -> Result<Vec<Answer>> {
    let text = read_text(path, MAX_TEXT_BYTES)?;
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(k, l)| (k + 1, l))
        .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'));
    let (hline, header) = lines
        .next()
        .ok_or_else(|| parse_err(path, 1, "empty: expected a header case,from,to,value"))?;
    let header = split_csv(header);
    let col = |name: &str| header.iter().position(|h| h == name);
    let (Some(c_case), Some(c_from), Some(c_to), Some(c_value)) =
        (col("case"), col("from"), col("to"), col("value"))
    else {
        return Err(parse_err(
            path,
            hline,
            format!(
                "header `{}` lacks one of case, from, to, value",
                header.join(",")
            ),
        ));
    };
    let (c_se, c_sec) = (col("stderr"), col("seconds"));
    let cases: HashMap<&str, &TableCase> =
        table.cases.iter().map(|c| (c.case.as_str(), c)).collect();
    let mut seen: HashMap<String, usize> = HashMap::new();
    let mut out = Vec::new();
    for (line, text) in lines {
        let f = split_csv(text);
        if f.len() != header.len() {
            return Err(parse_err(
                path,
                line,
                format!("{} fields, the header has {}", f.len(), header.len()),
            ));
        }
        let case = f[c_case].clone();
        let Some(tc) = cases.get(case.as_str()) else {
            return Err(parse_err(
                path,
                line,
                format!("no case `{case}` in suite {VERSION}"),
            ));
        };
        if f[c_from] != tc.from || f[c_to] != tc.to {
            return Err(parse_err(
                path,
                line,
                format!(
                    "case `{case}` compares `{}` to `{}`, not `{}` to `{}`",
                    tc.from, tc.to, f[c_from], f[c_to]
                ),
            ));
        }
        if let Some(first) = seen.insert(case.clone(), line) {
            return Err(parse_err(
                path,
                line,
                format!("case `{case}` answered again (first on line {first})"),
            ));
        }
        let opt = |c: Option<usize>, what: &str| -> Result<Option<f64>> {
            match c {
                Some(k) if !f[k].is_empty() => Ok(Some(number(path, line, what, &f[k])?)),
                _ => Ok(None),
            }
        };
        let stderr = opt(c_se, "stderr")?;
        if stderr.is_some_and(|s| s < 0.0) {
            return Err(parse_err(path, line, "stderr is negative"));
        }
        out.push(Answer {
            value: number(path, line, "value", &f[c_value])?,
            stderr,
            seconds: opt(c_sec, "seconds")?,
            from: tc.from.clone(),
            to: tc.to.clone(),
            case,
        });
    }
    Ok(out)
}

/// A sparse matrix as `(row, column, value)` triples, 0-based.
pub type Triples = Vec<(usize, usize, f64)>;

/// Reads a Matrix Market file (`coordinate` or `array`, `real`, `general`) of an `n x n`
/// matrix. Entries may come in any order; a repeated entry is an error.
pub fn read_mtx(path: &Path, n: usize) -> Result<Triples> {
    let text = read_text(path, MAX_TEXT_BYTES)?;
    let mut lines = text.lines().enumerate().map(|(k, l)| (k + 1, l));
    let (_, banner) = lines
        .next()
        .ok_or_else(|| parse_err(path, 1, "empty Matrix Market file"))?;
    let words: Vec<String> = banner
        .split_whitespace()
        .map(|w| w.to_ascii_lowercase())
        .collect();
    if words.len() != 5 || words[0] != "%%matrixmarket" || words[1] != "matrix" {
        return Err(parse_err(
            path,
            1,
            format!("not a Matrix Market header: `{banner}`"),
        ));
    }
    let dense = match words[2].as_str() {
        "coordinate" => false,
        "array" => true,
        w => {
            return Err(parse_err(
                path,
                1,
                format!("format `{w}`: expected coordinate or array"),
            ))
        }
    };
    if !(words[3] == "real" || words[3] == "double" || words[3] == "integer")
        || words[4] != "general"
    {
        return Err(parse_err(
            path,
            1,
            format!("`{} {}`: expected real general", words[3], words[4]),
        ));
    }
    let mut body = lines.filter(|(_, l)| !l.trim_start().starts_with('%') && !l.trim().is_empty());
    let (sline, size) = body
        .next()
        .ok_or_else(|| parse_err(path, 1, "no size line"))?;
    let dims: Vec<usize> = size
        .split_whitespace()
        .map(|w| w.parse())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| parse_err(path, sline, format!("size line `{size}` is not integers")))?;
    let want = if dense { 2 } else { 3 };
    if dims.len() != want || dims[0] != n || dims[1] != n {
        return Err(parse_err(
            path,
            sline,
            format!("size `{size}`: expected {n} x {n} (the patch table's rows)"),
        ));
    }
    let mut out = Vec::new();
    let mut seen = std::collections::HashSet::new();
    if dense {
        for (k, (line, l)) in body.enumerate() {
            if k >= n * n {
                return Err(parse_err(path, line, format!("more than {n} x {n} values")));
            }
            let x = number(path, line, "value", l.trim())?;
            // Column-major.
            out.push((k % n, k / n, x));
        }
        if out.len() != n * n {
            return Err(parse_err(
                path,
                sline,
                format!("{} values, expected {}", out.len(), n * n),
            ));
        }
        return Ok(out);
    }
    for (line, l) in body {
        let w: Vec<&str> = l.split_whitespace().collect();
        if w.len() != 3 {
            return Err(parse_err(
                path,
                line,
                format!("`{l}`: expected `row column value`"),
            ));
        }
        let idx = |s: &str| -> Result<usize> {
            match s.parse::<usize>() {
                Ok(k) if (1..=n).contains(&k) => Ok(k - 1),
                _ => Err(parse_err(
                    path,
                    line,
                    format!("index `{s}` is not in 1..={n}"),
                )),
            }
        };
        let (i, j) = (idx(w[0])?, idx(w[1])?);
        if !seen.insert((i, j)) {
            return Err(parse_err(
                path,
                line,
                format!("entry ({}, {}) repeated", i + 1, j + 1),
            ));
        }
        out.push((i, j, number(path, line, "value", w[2])?));
    }
    if out.len() != dims[2] {
        return Err(parse_err(
            path,
            sline,
            format!("{} entries, the size line says {}", out.len(), dims[2]),
        ));
    }
    Ok(out)
}

/// A patch table: area and surface of each patch.
pub fn read_patches(path: &Path, case: &TableCase) -> Result<Vec<(f64, String)>> {
    let text = read_text(path, MAX_TEXT_BYTES)?;
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(k, l)| (k + 1, l))
        .filter(|(_, l)| !l.trim().is_empty());
    let (hline, header) = lines
        .next()
        .ok_or_else(|| parse_err(path, 1, "empty patch table"))?;
    let header = split_csv(header);
    let col = |name: &str| header.iter().position(|h| h == name);
    let c_area =
        col("area").ok_or_else(|| parse_err(path, hline, "patch table has no `area` column"))?;
    let c_id = col("id");
    enum By {
        Surface(usize),
        Face(usize),
    }
    let by = match (col("surface"), col("material"), col("face")) {
        (Some(k), _, _) | (None, Some(k), _) => By::Surface(k),
        (None, None, Some(k)) => By::Face(k),
        _ => {
            return Err(parse_err(
                path,
                hline,
                "patch table has none of the columns surface, material, face",
            ))
        }
    };
    let mut face_surface = HashMap::new();
    for s in &case.surfaces {
        for &f in &s.faces {
            face_surface.insert(f, s.name.clone());
        }
    }
    let mut rows: Vec<Option<(f64, String)>> = Vec::new();
    for (k, (line, l)) in lines.enumerate() {
        let f = split_csv(l);
        if f.len() != header.len() {
            return Err(parse_err(
                path,
                line,
                format!("{} fields, the header has {}", f.len(), header.len()),
            ));
        }
        let id = match c_id {
            Some(c) => f[c]
                .parse::<usize>()
                .map_err(|_| parse_err(path, line, format!("id `{}` is not an index", f[c])))?,
            None => k,
        };
        let area = number(path, line, "area", &f[c_area])?;
        if area <= 0.0 {
            return Err(parse_err(
                path,
                line,
                format!("area {area} is not positive"),
            ));
        }
        let surface = match by {
            By::Surface(c) => {
                if case.surface(&f[c]).is_none() {
                    return Err(parse_err(
                        path,
                        line,
                        format!("no surface `{}` in case `{}`", f[c], case.case),
                    ));
                }
                f[c].clone()
            }
            By::Face(c) => {
                let face: usize = f[c].parse().map_err(|_| {
                    parse_err(path, line, format!("face `{}` is not an index", f[c]))
                })?;
                face_surface.get(&face).cloned().ok_or_else(|| {
                    parse_err(
                        path,
                        line,
                        format!("no face {face} in case `{}`", case.case),
                    )
                })?
            }
        };
        if id >= rows.len() {
            rows.resize(id + 1, None);
        }
        if rows[id].is_some() {
            return Err(parse_err(path, line, format!("patch {id} described twice")));
        }
        rows[id] = Some((area, surface));
    }
    rows.into_iter()
        .enumerate()
        .map(|(k, r)| r.ok_or_else(|| parse_err(path, hline, format!("no row for patch {k}"))))
        .collect()
}

/// Aggregates a patch matrix (and its standard errors) to `F_from,to` (see the
/// [module docs](self)); returns the value and the bar.
pub fn aggregate(
    patches: &[(f64, String)],
    f: &Triples,
    se: Option<&Triples>,
    from: &str,
    to: &str,
) -> (f64, Option<f64>) {
    let a_from: f64 = patches.iter().filter(|p| p.1 == from).map(|p| p.0).sum();
    let mut value = 0.0;
    for &(i, j, x) in f {
        if patches[i].1 == from && patches[j].1 == to {
            value += patches[i].0 * x;
        }
    }
    let bar = se.map(|se| {
        let mut var = 0.0;
        for &(i, j, s) in se {
            if patches[i].1 == from && patches[j].1 == to {
                let w = patches[i].0 / a_from;
                var += w * w * s * s;
            }
        }
        var.sqrt()
    });
    (value / a_from, bar)
}

/// Reads the answers in `dir/CASE/` for every case of `table` that has such a folder.
pub fn read_folders(dir: &Path, table: &Table) -> Result<Vec<Answer>> {
    if !dir.is_dir() {
        return Err(Error::Io {
            path: dir.to_path_buf(),
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "not a folder"),
        });
    }
    let mut out = Vec::new();
    for c in &table.cases {
        let d = dir.join(&c.case);
        if !d.is_dir() {
            continue;
        }
        let patches = read_patches(&d.join("patches.csv"), c)?;
        let f = read_mtx(&d.join("F.mtx"), patches.len())?;
        let se_path = d.join("stderr.mtx");
        let se = if se_path.exists() {
            Some(read_mtx(&se_path, patches.len())?)
        } else {
            None
        };
        let (value, stderr) = aggregate(&patches, &f, se.as_ref(), &c.from, &c.to);
        let prov = d.join("provenance.json");
        let seconds = if prov.exists() {
            let text = read_text(&prov, 1 << 20)?;
            let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| Error::Parse {
                path: prov.clone(),
                line: Some(e.line()),
                msg: e.to_string(),
            })?;
            v.get("seconds").and_then(|s| s.as_f64())
        } else {
            None
        };
        out.push(Answer {
            case: c.case.clone(),
            from: c.from.clone(),
            to: c.to.clone(),
            value,
            stderr,
            seconds,
        });
    }
    Ok(out)
}

fn median(mut xs: Vec<f64>) -> Option<f64> {
    if xs.is_empty() {
        return None;
    }
    xs.sort_by(f64::total_cmp);
    let m = xs.len() / 2;
    Some(if xs.len() % 2 == 1 {
        xs[m]
    } else {
        0.5 * (xs[m - 1] + xs[m])
    })
}

fn summarize(class: &str, rows: &[&CaseScore]) -> Summary {
    let answered: Vec<&&CaseScore> = rows.iter().filter(|r| r.value.is_some()).collect();
    let rel: Vec<f64> = answered.iter().filter_map(|r| r.relative).collect();
    let worst = answered
        .iter()
        .filter(|r| r.relative.is_some())
        .max_by(|a, b| a.relative.unwrap().total_cmp(&b.relative.unwrap()));
    let bars: Vec<f64> = answered.iter().filter_map(|r| r.sigmas).collect();
    let secs: Vec<f64> = answered.iter().filter_map(|r| r.seconds).collect();
    Summary {
        class: class.to_string(),
        cases: rows.len(),
        answered: answered.len(),
        median_relative: median(rel),
        worst_relative: worst.and_then(|w| w.relative),
        worst_case: worst.map(|w| w.case.clone()),
        with_bar: bars.len(),
        within_2_bars: (!bars.is_empty())
            .then(|| bars.iter().filter(|&&s| s <= 2.0).count() as f64 / bars.len() as f64),
        flagged: rows.iter().filter(|r| r.flagged).count(),
        seconds: (!secs.is_empty()).then(|| secs.iter().sum()),
    }
}

/// Scores `answers` against `table`.
pub fn score(table: &Table, answers: &[Answer], rule: Rule, tool: &str, command: &str) -> Score {
    let by_case: BTreeMap<&str, &Answer> = answers.iter().map(|a| (a.case.as_str(), a)).collect();
    let cases: Vec<CaseScore> = table
        .cases
        .iter()
        .map(|c| {
            let a = by_case.get(c.case.as_str());
            let value = a.map(|a| a.value);
            let error = value.map(|v| v - c.exact);
            let relative = error.map(|e| e.abs() / c.exact);
            let stderr = a.and_then(|a| a.stderr).filter(|&s| s > 0.0);
            let sigmas = match (error, stderr) {
                (Some(e), Some(s)) => Some(e.abs() / s),
                _ => None,
            };
            let flagged = relative.is_some_and(|r| r > rule.tolerance)
                && sigmas.is_none_or(|s| s > rule.sigmas);
            CaseScore {
                case: c.case.clone(),
                class: c.class.clone(),
                exact: c.exact,
                value,
                error,
                relative,
                stderr,
                sigmas,
                seconds: a.and_then(|a| a.seconds),
                flagged,
            }
        })
        .collect();
    let mut classes = Vec::new();
    for class in Class::ALL {
        let rows: Vec<&CaseScore> = cases.iter().filter(|c| c.class == class.name()).collect();
        if !rows.is_empty() {
            classes.push(summarize(class.name(), &rows));
        }
    }
    let all: Vec<&CaseScore> = cases.iter().collect();
    classes.push(summarize("all", &all));
    Score {
        suite: table.suite.clone(),
        tool: tool.to_string(),
        command: command.to_string(),
        rule,
        cases,
        classes,
    }
}

fn e(x: Option<f64>) -> String {
    x.map(|x| format!("{x:.2e}")).unwrap_or_else(|| "-".into())
}

/// The score as text: one line per case, then the summary per class.
pub fn report(s: &Score) -> String {
    let mut t = String::new();
    let _ = writeln!(t, "{} scored on {}", s.tool, s.suite);
    let _ = writeln!(
        t,
        "{:<28} {:<13} {:>18} {:>18} {:>9} {:>9} {:>8} {:>9}  flag",
        "case", "class", "exact", "value", "relative", "stderr", "err/bar", "seconds"
    );
    for c in &s.cases {
        let _ = writeln!(
            t,
            "{:<28} {:<13} {:>18.12} {:>18} {:>9} {:>9} {:>8} {:>9}  {}",
            c.case,
            c.class,
            c.exact,
            c.value
                .map(|v| format!("{v:.12}"))
                .unwrap_or_else(|| "missing".into()),
            e(c.relative),
            e(c.stderr),
            c.sigmas
                .map(|x| format!("{x:.2}"))
                .unwrap_or_else(|| "-".into()),
            c.seconds
                .map(|x| format!("{x:.3}"))
                .unwrap_or_else(|| "-".into()),
            if c.flagged { "FLAGGED" } else { "" }
        );
    }
    let _ = writeln!(
        t,
        "\n{:<13} {:>5} {:>8} {:>10} {:>10}  {:<26} {:>9} {:>8} {:>7} {:>9}",
        "class",
        "cases",
        "answered",
        "median rel",
        "worst rel",
        "worst case",
        "with bar",
        "<= 2 bar",
        "flagged",
        "seconds"
    );
    for c in &s.classes {
        let _ = writeln!(
            t,
            "{:<13} {:>5} {:>8} {:>10} {:>10}  {:<26} {:>9} {:>8} {:>7} {:>9}",
            c.class,
            c.cases,
            c.answered,
            e(c.median_relative),
            e(c.worst_relative),
            c.worst_case.as_deref().unwrap_or("-"),
            c.with_bar,
            c.within_2_bars
                .map(|x| format!("{:.0}%", 100.0 * x))
                .unwrap_or_else(|| "-".into()),
            c.flagged,
            c.seconds
                .map(|x| format!("{x:.3}"))
                .unwrap_or_else(|| "-".into()),
        );
    }
    let flagged = s.flagged();
    let _ = writeln!(
        t,
        "flagged (relative error > {:e} and, with a bar, error > {} bars): {}",
        s.rule.tolerance,
        s.rule.sigmas,
        if flagged.is_empty() {
            "none".to_string()
        } else {
            flagged.join(", ")
        }
    );
    t
}

/// The per-case scores as CSV.
pub fn to_csv(s: &Score) -> String {
    let mut t = String::from(
        "suite,tool,case,class,exact,value,error,relative,stderr,sigmas,seconds,flagged\n",
    );
    let o = |x: Option<f64>| x.map(|x| format!("{x:?}")).unwrap_or_default();
    for c in &s.cases {
        let _ = writeln!(
            t,
            "{},{},{},{},{:?},{},{},{},{},{},{},{}",
            s.suite,
            csv_field(&s.tool),
            c.case,
            c.class,
            c.exact,
            o(c.value),
            o(c.error),
            o(c.relative),
            o(c.stderr),
            o(c.sigmas),
            o(c.seconds),
            c.flagged
        );
    }
    t
}

/// Writes the score as JSON (`.json`) or CSV (any other extension) to `path`.
pub fn write(path: &Path, s: &Score) -> Result<PathBuf> {
    let text = if path.extension().is_some_and(|e| e == "json") {
        serde_json::to_string_pretty(s).map_err(|e| Error::Output {
            path: path.to_path_buf(),
            msg: e.to_string(),
        })?
    } else {
        to_csv(s)
    };
    write_atomic(path, |tmp| {
        std::fs::write(tmp, &text).map_err(|e| Error::io(tmp, e))
    })?;
    Ok(path.to_path_buf())
}

/// Reads a score written by [`fn@write`] as JSON.
pub fn read(path: &Path) -> Result<Score> {
    let text = read_text(path, MAX_TEXT_BYTES)?;
    serde_json::from_str(&text).map_err(|e| Error::Parse {
        path: path.to_path_buf(),
        line: Some(e.line()),
        msg: format!("not a suite score: {e}"),
    })
}
