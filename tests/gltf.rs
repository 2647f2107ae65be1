//! `mesh.glb`: one named node per object, in metres, colours within [0, 1], and, when Node.js
//! is there, no error or warning from the Khronos glTF validator
//! (`scripts/validate-gltf.sh`).

use std::path::{Path, PathBuf};
use std::process::Command;

use radiosity::mesh::Resolution;
use radiosity::pipeline::{self, BakeConfig, Quiet};
use radiosity::scene::Units;

fn temp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("radiosity-gltf-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The JSON chunk of a `.glb` file, after checking the container's header.
fn glb_json(path: &Path) -> serde_json::Value {
    let b = std::fs::read(path).expect("mesh.glb");
    let u32_at = |k: usize| u32::from_le_bytes(b[k..k + 4].try_into().unwrap()) as usize;
    assert_eq!(&b[0..4], b"glTF");
    assert_eq!(u32_at(4), 2, "GLB version");
    assert_eq!(u32_at(8), b.len(), "GLB length");
    assert_eq!(&b[16..20], b"JSON");
    let n = u32_at(12);
    assert_eq!(&b[20 + n + 4..20 + n + 8], b"BIN\0");
    serde_json::from_slice(&b[20..20 + n]).expect("JSON chunk")
}

fn names(root: &serde_json::Value, what: &str) -> Vec<String> {
    root[what]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x["name"].as_str().unwrap().to_string())
        .collect()
}

/// Runs `scripts/validate-gltf.sh` on `files`; `None` (with the reason printed) when node
/// or the validator cannot be had here.
fn validate(files: &[PathBuf]) -> Option<String> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/validate-gltf.sh");
    let node = Command::new("node").arg("--version").output();
    if !node.is_ok_and(|o| o.status.success()) {
        eprintln!("glTF validator skipped: node is not installed");
        return None;
    }
    let out = Command::new("bash")
        .arg(&script)
        .args(files)
        .output()
        .expect("bash runs");
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    let stderr = String::from_utf8_lossy(&out.stderr);
    match out.status.code() {
        Some(2) => {
            eprintln!("glTF validator skipped: {stderr}");
            None
        }
        Some(0) => {
            eprintln!("{stdout}");
            Some(stdout)
        }
        _ => panic!("the glTF validator finds errors:\n{stdout}\n{stderr}"),
    }
}

#[test]
fn bakes_write_a_glb_with_named_objects_in_metres_that_validates() {
    let dir = temp_dir("bake");
    // The Cornell box says `#@units mm`: 0.556 m wide.
    let cornell = BakeConfig {
        out_dir: dir.join("cornell"),
        resolution: Resolution::Patches(150),
        preview: (32, 32),
        ..BakeConfig::default()
    };
    pipeline::bake(&cornell, &Quiet).expect("Cornell bake");
    // An OBJ file of two objects with no units, baked with --units cm.
    let obj = dir.join("room.obj");
    std::fs::write(
        dir.join("room.mtl"),
        "newmtl wall\nKd 0.5 0.5 0.5\nnewmtl lamp\nKd 0 0 0\nKe 5 5 5\n",
    )
    .unwrap();
    std::fs::write(
        &obj,
        "mtllib room.mtl\no Floor plate\nusemtl wall\n\
         v 0 0 0\nv 200 0 0\nv 200 0 100\nv 0 0 100\nf 1 4 3 2\n\
         o Lamp\nusemtl lamp\nv 50 80 25\nv 150 80 25\nv 150 80 75\nv 50 80 75\nf 5 6 7 8\n",
    )
    .unwrap();
    let room = BakeConfig {
        scene: obj.to_string_lossy().into_owned(),
        out_dir: dir.join("room"),
        resolution: Resolution::Patches(60),
        preview: (32, 32),
        units: Some(Units::Centimetres),
        ..BakeConfig::default()
    };
    let s = pipeline::bake(&room, &Quiet).expect("room bake");
    assert!(
        s.files.iter().any(|f| f.ends_with("mesh.glb")),
        "{:?}",
        s.files
    );

    let c = glb_json(&dir.join("cornell/mesh.glb"));
    assert_eq!(
        names(&c, "nodes"),
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
    assert_eq!(names(&c, "meshes"), names(&c, "nodes"));
    let pos_max = |root: &serde_json::Value, mesh: usize| {
        let a = root["meshes"][mesh]["primitives"][0]["attributes"]["POSITION"]
            .as_u64()
            .unwrap() as usize;
        let m = &root["accessors"][a]["max"];
        [0, 1, 2].map(|k| m[k].as_f64().unwrap())
    };
    // The floor reaches x = 552.8 mm, z = 559.2 mm; y = 0 is the floor, +y up.
    let floor = pos_max(&c, 0);
    assert!(
        (floor[0] - 0.5528).abs() < 1e-6 && floor[1] == 0.0,
        "{floor:?}"
    );
    assert!((pos_max(&c, 1)[1] - 0.5488).abs() < 1e-6, "ceiling height");
    assert_eq!(c["asset"]["extras"]["scene_units"], "mm");

    let r = glb_json(&dir.join("room/mesh.glb"));
    assert_eq!(names(&r, "nodes"), ["Floor plate", "Lamp"]);
    let lamp = pos_max(&r, 1);
    assert!(
        (lamp[0] - 1.5).abs() < 1e-6 && (lamp[1] - 0.8).abs() < 1e-6,
        "{lamp:?}"
    );
    // COLOR_0 is float (the writer clamps it to [0, 1]; the validator checks it).
    for root in [&c, &r] {
        for m in root["meshes"].as_array().unwrap() {
            let a = m["primitives"][0]["attributes"]["COLOR_0"]
                .as_u64()
                .unwrap();
            assert_eq!(root["accessors"][a as usize]["componentType"], 5126);
        }
    }
    let ply = std::fs::read(dir.join("room/mesh.ply")).unwrap();
    let head = String::from_utf8_lossy(&ply[..400]);
    assert!(head.contains("comment units cm\ncomment up +y\n"), "{head}");

    if let Some(report) = validate(&[dir.join("cornell/mesh.glb"), dir.join("room/mesh.glb")]) {
        assert_eq!(
            report.matches("0 errors, 0 warnings").count(),
            2,
            "{report}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
