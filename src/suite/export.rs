//! `radiosity suite export DIR`: the cases as OBJ/MTL files and the table that names, for
//! each, the surfaces to compare, the exact value and its source.
//!
//! Layout of `DIR`:
//! - `suite.json`: `{"suite": VERSION, "cases": [...]}`, one [`TableCase`] per case;
//! - `suite.csv`: the same table, one row per case: `case, class, geometry, from, to,
//!   from_faces, to_faces, exact, source` (face indices space-separated);
//! - `cases/NAME.obj`, `cases/NAME.mtl`: the geometry. Each surface is an OBJ object and
//!   group (`o NAME`, `g NAME`) with its own material of the same name, so a program can
//!   tell the surfaces apart by object, group, material or face index (0-based, in the
//!   order of the `f` lines). The from-surface's material emits (`Ke 1 1 1`, which
//!   programs that need an emitter require); every material has `Kd 0.5 0.5 0.5`.
//!   Coordinates are written with Rust's shortest round-trip formatting, so the files hold
//!   the catalogue's `f64` values exactly.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{Case, VERSION};
use crate::error::{Error, Result};
use crate::output::write_atomic;

/// One surface of a case in the table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TableSurface {
    /// Name (OBJ object, group and material).
    pub name: String,
    /// 0-based indices of its faces, in OBJ `f` order.
    pub faces: Vec<usize>,
    /// Total area.
    pub area: f64,
}

/// One row of the table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TableCase {
    /// Case name.
    pub case: String,
    /// Difficulty class ([`super::Class::name`]).
    pub class: String,
    /// What it is.
    pub about: String,
    /// OBJ file, relative to the table.
    pub geometry: String,
    /// From-surface name.
    pub from: String,
    /// To-surface name.
    pub to: String,
    /// Exact `F_from,to`.
    pub exact: f64,
    /// Where the exact value comes from.
    pub source: String,
    /// Every surface of the scene.
    pub surfaces: Vec<TableSurface>,
}

impl TableCase {
    /// The surface named `name`.
    pub fn surface(&self, name: &str) -> Option<&TableSurface> {
        self.surfaces.iter().find(|s| s.name == name)
    }
}

/// The whole table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Table {
    /// Suite version ([`VERSION`]).
    pub suite: String,
    /// The cases.
    pub cases: Vec<TableCase>,
}

/// The table row of a case.
pub fn table_case(c: &Case) -> TableCase {
    TableCase {
        case: c.name.clone(),
        class: c.class.name().to_string(),
        about: c.about.clone(),
        geometry: format!("cases/{}.obj", c.name),
        from: c.surfaces[c.from].name.clone(),
        to: c.surfaces[c.to].name.clone(),
        exact: c.exact,
        source: c.source.clone(),
        surfaces: (0..c.surfaces.len())
            .map(|s| TableSurface {
                name: c.surfaces[s].name.clone(),
                faces: c.face_indices(s),
                area: c.surfaces[s].area(),
            })
            .collect(),
    }
}

/// The OBJ and MTL text of a case.
pub fn obj_text(c: &Case) -> (String, String) {
    let mut obj = String::new();
    let t = table_case(c);
    let _ = writeln!(obj, "# {VERSION} case {}: {}", c.name, c.about);
    let _ = writeln!(
        obj,
        "# compare: from `{}` (faces {:?}) to `{}` (faces {:?}); exact F = {:?} ({})",
        t.from,
        t.surface(&t.from).map(|s| &s.faces),
        t.to,
        t.surface(&t.to).map(|s| &s.faces),
        c.exact,
        c.source
    );
    let _ = writeln!(obj, "mtllib {}.mtl", c.name);
    let mut mtl = format!("# {VERSION} case {}\n", c.name);
    let mut next = 1usize;
    for (k, s) in c.surfaces.iter().enumerate() {
        let _ = writeln!(obj, "o {}\ng {}\nusemtl {}", s.name, s.name, s.name);
        for p in &s.polygons {
            for x in p {
                let _ = writeln!(obj, "v {:?} {:?} {:?}", x.x, x.y, x.z);
            }
            let idx: Vec<String> = (next..next + p.len()).map(|i| i.to_string()).collect();
            let _ = writeln!(obj, "f {}", idx.join(" "));
            next += p.len();
        }
        let ke = if k == c.from { "1 1 1" } else { "0 0 0" };
        let _ = writeln!(mtl, "newmtl {}\nKd 0.5 0.5 0.5\nKe {ke}", s.name);
    }
    (obj, mtl)
}

pub use crate::output::csv_field;

fn write_text(path: &Path, text: &str) -> Result<()> {
    write_atomic(path, |tmp| {
        std::fs::write(tmp, text).map_err(|e| Error::io(tmp, e))
    })
}

/// Writes the cases and the table into `dir` (created if missing); returns the table.
pub fn export(dir: &Path, cases: &[Case]) -> Result<Table> {
    let case_dir = dir.join("cases");
    std::fs::create_dir_all(&case_dir).map_err(|e| Error::io(&case_dir, e))?;
    let mut csv = String::from("case,class,geometry,from,to,from_faces,to_faces,exact,source\n");
    let mut rows = Vec::new();
    for c in cases {
        let (obj, mtl) = obj_text(c);
        write_text(&case_dir.join(format!("{}.obj", c.name)), &obj)?;
        write_text(&case_dir.join(format!("{}.mtl", c.name)), &mtl)?;
        let t = table_case(c);
        let faces = |n: &str| {
            t.surface(n)
                .map(|s| {
                    s.faces
                        .iter()
                        .map(|f| f.to_string())
                        .collect::<Vec<_>>()
                        .join(" ")
                })
                .unwrap_or_default()
        };
        let _ = writeln!(
            csv,
            "{},{},{},{},{},{},{},{:?},{}",
            t.case,
            t.class,
            t.geometry,
            t.from,
            t.to,
            faces(&t.from),
            faces(&t.to),
            t.exact,
            csv_field(&t.source)
        );
        rows.push(t);
    }
    let table = Table {
        suite: VERSION.to_string(),
        cases: rows,
    };
    let json_path = dir.join("suite.json");
    let json = serde_json::to_string_pretty(&table).map_err(|e| Error::Output {
        path: json_path.clone(),
        msg: e.to_string(),
    })?;
    write_text(&json_path, &json)?;
    write_text(&dir.join("suite.csv"), &csv)?;
    Ok(table)
}

/// Reads `suite.json` from `dir` (or the file itself when `dir` is a file), refusing a
/// table of another suite version.
pub fn read_table(dir: &Path) -> Result<(Table, PathBuf)> {
    let path = if dir.is_dir() {
        dir.join("suite.json")
    } else {
        dir.to_path_buf()
    };
    let text = crate::input::read_text(&path, 64 << 20)?;
    let table: Table = serde_json::from_str(&text).map_err(|e| Error::Parse {
        path: path.clone(),
        line: Some(e.line()),
        msg: format!("not a suite table: {e}"),
    })?;
    if table.suite != VERSION {
        return Err(Error::Parse {
            path,
            line: None,
            msg: format!(
                "suite version `{}`, this program scores `{VERSION}`",
                table.suite
            ),
        });
    }
    let base = path.parent().map(Path::to_path_buf).unwrap_or_default();
    Ok((table, base))
}
