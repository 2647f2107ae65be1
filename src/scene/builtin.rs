//! Built-in scenes, embedded from the `scenes/` folder so that they work from any
//! directory: `cornell`, `plates-perpendicular`, `plates-parallel`, `cube`, `shelf`.

use std::path::{Path, PathBuf};

use super::{obj, Scene};
use crate::error::{Error, Result};

/// Names of the built-in scenes.
pub const NAMES: &[&str] = &[
    "cornell",
    "plates-perpendicular",
    "plates-parallel",
    "cube",
    "shelf",
];

/// One line on what a built-in scene is and what it is for (`radiosity scenes`).
pub fn describe(name: &str) -> Option<&'static str> {
    Some(match name {
        "cornell" => "the Cornell box, from Cornell's published data (mm)",
        "plates-perpendicular" => "unit squares at 90° on an edge: F = 0.2000438 (C-14)",
        "plates-parallel" => "opposed unit squares 1 apart: F = 0.1998249 (C-11)",
        "cube" => "the closed unit cube facing inward: rows sum to 1",
        "shelf" => "the notes' infinite shelf (3 strips, L = 33)",
        _ => return None,
    })
}

/// OBJ text and the MTL files it may reference, per built-in scene.
fn files(name: &str) -> Option<(&'static str, &'static [(&'static str, &'static str)])> {
    const CORNELL_MTL: &[(&str, &str)] =
        &[("cornell.mtl", include_str!("../../scenes/cornell.mtl"))];
    const PLATES_MTL: &[(&str, &str)] = &[("plates.mtl", include_str!("../../scenes/plates.mtl"))];
    const CUBE_MTL: &[(&str, &str)] = &[("cube.mtl", include_str!("../../scenes/cube.mtl"))];
    const SHELF_MTL: &[(&str, &str)] = &[("shelf.mtl", include_str!("../../scenes/shelf.mtl"))];
    Some(match name {
        "cornell" => (include_str!("../../scenes/cornell.obj"), CORNELL_MTL),
        "plates-perpendicular" => (
            include_str!("../../scenes/plates-perpendicular.obj"),
            PLATES_MTL,
        ),
        "plates-parallel" => (include_str!("../../scenes/plates-parallel.obj"), PLATES_MTL),
        "cube" => (include_str!("../../scenes/cube.obj"), CUBE_MTL),
        "shelf" => (include_str!("../../scenes/shelf.obj"), SHELF_MTL),
        _ => return None,
    })
}

/// The built-in scene `name`, or `None` when there is no such built-in scene.
pub fn load(name: &str) -> Result<Option<Scene>> {
    let Some((obj_text, mtls)) = files(name) else {
        return Ok(None);
    };
    let label = PathBuf::from(format!("scenes/{name}.obj"));
    let mut scene = obj::parse(name, &label, obj_text, &|lib: &str| {
        mtls.iter()
            .find(|(n, _)| *n == lib)
            .map(|(n, t)| (Path::new("scenes").join(n), t.to_string()))
            .ok_or_else(|| Error::Parse {
                path: label.clone(),
                line: None,
                msg: format!("built-in scene refers to unknown mtllib `{lib}`"),
            })
    })?;
    scene.source = format!("builtin:{name}");
    Ok(Some(scene))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_builtin_is_described_in_80_columns() {
        let width = NAMES.iter().map(|n| n.len()).max().unwrap();
        for name in NAMES {
            let d = describe(name).unwrap_or_else(|| panic!("{name}: no description"));
            assert!(width + 2 + d.chars().count() <= 80, "{name}: {d}");
        }
    }

    #[test]
    fn all_builtins_load() {
        for name in super::NAMES {
            let s = super::load(name).unwrap().unwrap();
            assert!(!s.faces.is_empty(), "{name}");
            assert!(s.warnings.is_empty(), "{name}: {:?}", s.warnings);
            s.require_emitter().unwrap();
        }
    }

    #[test]
    fn builtins_name_their_objects_and_the_cornell_box_its_units() {
        let objects = |name: &str| super::load(name).unwrap().unwrap().objects;
        assert_eq!(
            objects("cornell"),
            [
                "floor",
                "ceiling",
                "back_wall",
                "short_block",
                "tall_block",
                "light",
                "red_wall",
                "green_wall"
            ]
        );
        assert_eq!(objects("plates-parallel"), ["emitter", "receiver"]);
        assert_eq!(objects("plates-perpendicular"), ["emitter", "receiver"]);
        assert_eq!(objects("cube"), ["z0", "z1", "y0", "y1", "x0", "x1"]);
        assert_eq!(objects("shelf"), ["floor_A", "back_B", "top_C"]);
        let cornell = super::load("cornell").unwrap().unwrap();
        assert_eq!(cornell.units, Some(crate::scene::Units::Millimetres));
        assert_eq!(super::load("cube").unwrap().unwrap().units, None);
    }
}
