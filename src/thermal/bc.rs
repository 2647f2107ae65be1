//! The boundary-conditions file of the thermal mode: per material, a gray emissivity and a
//! temperature or a net flux, as CSV.
//!
//! ```text
//! # comments and blank lines are skipped
//! material,emissivity,temperature,flux
//! hot,0.8,1000,
//! walls,0.3,,0
//! ```
//!
//! The header names the columns, in any order: `material` and `emissivity`, and
//! `temperature` (K) and/or `flux` (W/m², net, leaving the surface; 0 is an adiabatic,
//! re-radiating surface). Each row gives exactly one of the two. A row sets the material's
//! thermal properties, replacing those of an MTL `#@thermal` line. Errors name the file and
//! line: an unknown column or material, a material given twice, a value out of range
//! ([`crate::scene::Thermal::validate`]).

use std::path::Path;

use crate::error::{Error, Result};
use crate::input::read_text;
use crate::scene::{Boundary, Scene, Thermal};

/// Largest boundary-conditions file read, in bytes.
pub const MAX_BYTES: u64 = 16 << 20;

/// One row of the file.
#[derive(Clone, Debug, PartialEq)]
pub struct Row {
    /// The material it applies to.
    pub material: String,
    /// Its thermal properties.
    pub thermal: Thermal,
    /// 1-based line.
    pub line: usize,
}

/// Reads and parses a boundary-conditions file.
pub fn read(path: &Path) -> Result<Vec<Row>> {
    let text = read_text(path, MAX_BYTES)?;
    parse(path, &text)
}

/// Parses boundary-conditions text (`path` names it in messages).
pub fn parse(path: &Path, text: &str) -> Result<Vec<Row>> {
    let bad = |line: usize, msg: String| Error::Parse {
        path: path.to_path_buf(),
        line: Some(line),
        msg,
    };
    let mut header: Option<Vec<String>> = None;
    let mut rows: Vec<Row> = Vec::new();
    for (k, raw) in text.lines().enumerate() {
        let line = k + 1;
        let trimmed = raw.trim();
        if trimmed.is_empty() || trimmed.starts_with('#') {
            continue;
        }
        let cells: Vec<&str> = trimmed.split(',').map(str::trim).collect();
        let Some(cols) = &header else {
            let cols: Vec<String> = cells.iter().map(|c| c.to_ascii_lowercase()).collect();
            for c in &cols {
                if !["material", "emissivity", "temperature", "flux"].contains(&c.as_str()) {
                    return Err(bad(
                        line,
                        format!(
                            "unknown column `{c}` (the header names `material`, \
                             `emissivity`, `temperature` and/or `flux`)"
                        ),
                    ));
                }
                if cols.iter().filter(|d| *d == c).count() > 1 {
                    return Err(bad(line, format!("column `{c}` given twice")));
                }
            }
            for need in ["material", "emissivity"] {
                if !cols.iter().any(|c| c == need) {
                    return Err(bad(line, format!("the header has no `{need}` column")));
                }
            }
            if !cols.iter().any(|c| c == "temperature" || c == "flux") {
                return Err(bad(
                    line,
                    "the header needs a `temperature` or a `flux` column".into(),
                ));
            }
            header = Some(cols);
            continue;
        };
        if cells.len() != cols.len() {
            return Err(bad(
                line,
                format!(
                    "{} fields, but the header has {} columns",
                    cells.len(),
                    cols.len()
                ),
            ));
        }
        let cell = |name: &str| {
            cols.iter()
                .position(|c| c == name)
                .map(|p| cells[p])
                .filter(|v| !v.is_empty())
        };
        let number = |name: &str| -> Result<Option<f64>> {
            match cell(name) {
                None => Ok(None),
                Some(v) => match v.parse::<f64>() {
                    Ok(x) if x.is_finite() => Ok(Some(x)),
                    _ => Err(bad(line, format!("{name} `{v}` is not a finite number"))),
                },
            }
        };
        let material = cell("material")
            .ok_or_else(|| bad(line, "empty material name".into()))?
            .to_string();
        if let Some(prev) = rows.iter().find(|r| r.material == material) {
            return Err(bad(
                line,
                format!(
                    "material `{material}` is already given on line {}",
                    prev.line
                ),
            ));
        }
        let emissivity =
            number("emissivity")?.ok_or_else(|| bad(line, "empty emissivity".into()))?;
        let boundary = match (number("temperature")?, number("flux")?) {
            (Some(t), None) => Boundary::Temperature(t),
            (None, Some(q)) => Boundary::Flux(q),
            (Some(_), Some(_)) => {
                return Err(bad(
                    line,
                    format!("material `{material}`: give a temperature or a flux, not both"),
                ))
            }
            (None, None) => {
                return Err(bad(
                    line,
                    format!("material `{material}`: no temperature and no flux"),
                ))
            }
        };
        let thermal = Thermal {
            emissivity,
            boundary,
        };
        thermal.validate().map_err(|msg| Error::Material {
            path: path.to_path_buf(),
            line: Some(line),
            material: material.clone(),
            msg,
        })?;
        rows.push(Row {
            material,
            thermal,
            line,
        });
    }
    if header.is_none() {
        return Err(Error::Parse {
            path: path.to_path_buf(),
            line: None,
            msg: "no header line (`material,emissivity,temperature,flux`)".into(),
        });
    }
    Ok(rows)
}

/// Sets the thermal properties of the materials the rows name; a name the scene does not
/// have is refused with its line.
pub fn apply(scene: &mut Scene, path: &Path, rows: &[Row]) -> Result<()> {
    for r in rows {
        let k = scene
            .material_index(&r.material)
            .ok_or_else(|| Error::Parse {
                path: path.to_path_buf(),
                line: Some(r.line),
                msg: format!(
                    "no material `{}` in scene `{}` (it has: {})",
                    r.material,
                    scene.source,
                    scene
                        .materials
                        .iter()
                        .map(|m| m.name.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            })?;
        scene.materials[k].thermal = Some(r.thermal);
    }
    Ok(())
}

/// Refuses a scene in which some face's material has no thermal properties, naming the
/// material (before any work).
pub fn require(scene: &Scene) -> Result<()> {
    for f in &scene.faces {
        let m = &scene.materials[f.material as usize];
        if m.thermal.is_none() {
            return Err(Error::Scene {
                scene: scene.source.clone(),
                msg: format!(
                    "material `{}` (used by the face on line {}) has no thermal properties: \
                     add `#@thermal emissivity E temperature K` (or `flux W_PER_M2`) after its \
                     `newmtl`, or a row to the --bc file",
                    m.name, f.line
                ),
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_refuses_with_lines() {
        let p = Path::new("bc.csv");
        let rows = parse(
            p,
            "# plates\nmaterial, emissivity, temperature, flux\nhot,0.8,1000,\nwalls,0.3,,0\n",
        )
        .unwrap();
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[0].thermal.boundary, Boundary::Temperature(1000.0));
        assert_eq!(rows[1].thermal.boundary, Boundary::Flux(0.0));
        assert_eq!(rows[1].line, 4);
        let err = |t: &str| parse(p, t).unwrap_err().to_string();
        let h = "material,emissivity,temperature,flux\n";
        assert!(err(&format!("{h}a,0,300,\n")).contains("bc.csv:2"));
        assert!(err(&format!("{h}a,1.5,300,\n")).contains("emissivity 1.5"));
        assert!(err(&format!("{h}a,0.5,300,1\n")).contains("not both"));
        assert!(err(&format!("{h}a,0.5,,\n")).contains("no temperature"));
        assert!(err(&format!("{h}a,0.5,-1,\n")).contains("temperature -1"));
        assert!(err(&format!("{h}a,0.5,nan,\n")).contains("not a finite"));
        assert!(err(&format!("{h}a,0.5,3,\na,0.5,3,\n")).contains("line 2"));
        assert!(err(&format!("{h}a,0.5,3\n")).contains("3 fields"));
        assert!(err("material,emissivity,colour\n").contains("unknown column"));
        assert!(err("material,temperature\n").contains("emissivity"));
        assert!(err("# nothing\n").contains("no header"));
    }
}
