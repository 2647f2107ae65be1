//! Lightmaps: a furnace bakes to its known radiosity in every texel; a lit floor's texels
//! equal the output mesh's Gouraud value at their surface points, found in 3D; texels
//! around a chart are dilated; faces without UVs are refused before any work; UVs go
//! through the triangulation of polygons.

use glam::{DVec2, DVec3};
use radiosity::mesh::{PatchSet, Resolution};
use radiosity::output::{self, lightmap};
use radiosity::pipeline::{self, BakeConfig, Quiet};
use radiosity::scene::Scene;

fn temp_dir(tag: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("radiosity-lm-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

/// The inward unit cube (a furnace: rho 0.5, E 1, so B = 2 everywhere) with each face in
/// its own tile of a 3 x 2 grid of the UV square, 0.05 inside the tile's edges.
fn uv_cube(dir: &std::path::Path) -> String {
    let mut obj = String::from(
        "mtllib cube.mtl\nusemtl wall\no cube\n\
         v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\nv 1 1 1\nv 0 1 1\n",
    );
    for k in 0..6 {
        let (u0, v0) = ((k % 3) as f64 / 3.0 + 0.05, (k / 3) as f64 / 2.0 + 0.05);
        let (du, dv) = (1.0 / 3.0 - 0.1, 0.5 - 0.1);
        for (a, b) in [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)] {
            obj.push_str(&format!("vt {} {}\n", u0 + a * du, v0 + b * dv));
        }
    }
    let faces = [
        [1, 2, 3, 4],
        [5, 8, 7, 6],
        [1, 5, 6, 2],
        [4, 3, 7, 8],
        [1, 4, 8, 5],
        [2, 6, 7, 3],
    ];
    for (k, f) in faces.iter().enumerate() {
        obj.push('f');
        for (c, v) in f.iter().enumerate() {
            obj.push_str(&format!(" {v}/{}", 4 * k + c + 1));
        }
        obj.push('\n');
    }
    std::fs::write(dir.join("cube.obj"), obj).expect("obj");
    std::fs::write(
        dir.join("cube.mtl"),
        "newmtl wall\nKd 0.5 0.5 0.5\nKe 1 1 1\n",
    )
    .expect("mtl");
    dir.join("cube.obj").to_string_lossy().into_owned()
}

#[test]
fn a_furnace_lightmap_holds_its_known_radiosity_and_is_dilated() {
    let dir = temp_dir("furnace");
    let cfg = BakeConfig {
        scene: uv_cube(&dir),
        out_dir: dir.join("out"),
        resolution: Resolution::MaxEdge(0.2),
        preview: (16, 16),
        lightmap: Some(64),
        ..BakeConfig::default()
    };
    let s = pipeline::bake(&cfg, &Quiet).expect("bake");
    let out = dir.join("out");
    assert!(
        s.files.contains(&out.join("lightmap-cube.exr")),
        "{:?}",
        s.files
    );
    // Listed in the manifest, with the index.
    let manifest = output::Manifest::read(&out).expect("manifest");
    manifest.verify(&out).expect("whole folder");
    for name in ["lightmap-cube.exr", "lightmaps.json"] {
        assert!(manifest.files.iter().any(|f| f.name == name), "{name}");
    }
    let (rgba, size, object, back) = lightmap::read(&out.join("lightmap-cube.exr")).unwrap();
    assert_eq!((size, object.as_str(), back), (64, "cube", false));
    let (mut covered, mut dilated) = (0, 0);
    for y in 0..size {
        for x in 0..size {
            let t = rgba[y * size + x];
            let (u, v) = ((x as f64 + 0.5) / 64.0, 1.0 - (y as f64 + 0.5) / 64.0);
            // Inside a face's rectangle, a texel or more from its edges: covered.
            let (fu, fv) = ((u * 3.0).fract(), (v * 2.0).fract());
            let du = (fu - 0.5).abs() * 64.0 / 3.0; // texels from the tile's centre, across u
            let dv = (fv - 0.5).abs() * 64.0 / 2.0;
            let half_u = (0.5 - 0.15) * 64.0 / 3.0; // the face spans 0.05..0.95 of the tile
            let half_v = (0.5 - 0.1) * 64.0 / 2.0;
            if du < half_u - 1.0 && dv < half_v - 1.0 {
                assert_eq!(t[3], 1.0, "({x}, {y}) uncovered");
                for c in 0..3 {
                    assert!((t[c] - 2.0).abs() < 1e-5, "({x}, {y}): {t:?}");
                }
                covered += 1;
            } else if t[3] == 0.0 && t[0] != 0.0 {
                // A dilated texel: the chart's value, coverage 0.
                assert!((t[0] - 2.0).abs() < 1e-5, "({x}, {y}): {t:?}");
                dilated += 1;
            }
            if t[3] == 1.0 {
                assert!((t[0] - 2.0).abs() < 1e-5, "({x}, {y}): {t:?}");
            }
        }
    }
    assert!(covered > 6 * 100, "{covered}");
    assert!(dilated > 6 * 4 * 20, "{dilated} dilated texels");
    let index: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("lightmaps.json")).unwrap())
            .unwrap();
    assert_eq!(index["resolution"], 64);
    assert_eq!(index["lightmaps"][0]["file"], "lightmap-cube.exr");
    assert_eq!(index["lightmaps"][0]["texels_overlapping"], 0);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A 2 x 2 floor (y = 0, facing up, UVs u = x / 2, v = 1 - z / 2) lit by a small lamp
/// above one corner, its own object with its own UVs.
fn lit_floor(dir: &std::path::Path) -> String {
    let obj = "mtllib f.mtl\n\
        o floor\nusemtl floor\nv 0 0 0\nv 0 0 2\nv 2 0 2\nv 2 0 0\n\
        vt 0 1\nvt 0 0\nvt 1 0\nvt 1 1\nf 1/1 2/2 3/3 4/4\n\
        o lamp\nusemtl lamp\nv 0.2 1 0.2\nv 0.6 1 0.2\nv 0.6 1 0.6\nv 0.2 1 0.6\n\
        vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 5/5 6/6 7/7 8/8\n";
    std::fs::write(dir.join("floor.obj"), obj).unwrap();
    std::fs::write(
        dir.join("f.mtl"),
        "newmtl floor\nKd 0.5 0.5 0.5\nnewmtl lamp\nKe 5 5 5\n",
    )
    .unwrap();
    dir.join("floor.obj").to_string_lossy().into_owned()
}

#[test]
fn texels_equal_the_mesh_value_at_their_surface_point() {
    let dir = temp_dir("gradient");
    let scene = Scene::load(&lit_floor(&dir)).expect("scene");
    let patches = PatchSet::build(&scene, Resolution::MaxEdge(0.3)).expect("patches");
    // A smooth field per patch (the test is about the map, not the solve): a gradient and
    // a bump across the floor.
    let b: Vec<[f64; 3]> = (0..patches.len())
        .map(|i| {
            let c = patches.centroid[i];
            let v = 1.0 + 0.7 * c.x - 0.2 * c.z
                + (-(c - DVec3::new(0.4, 0.0, 0.4)).length_squared()).exp();
            [v, 2.0 * v, 0.5]
        })
        .collect();
    let verts = output::interpolate(&patches, &b, 30.0);
    let maps = lightmap::render(&scene, &patches, &verts, 48);
    let floor = maps
        .iter()
        .find(|m| scene.objects[m.object as usize] == "floor")
        .unwrap();
    let mut checked = 0;
    for y in 0..48 {
        for x in 0..48 {
            let t = floor.rgba[y * 48 + x];
            if t[3] != 1.0 {
                continue;
            }
            // The texel's surface point, by the floor's UV map, in 3D.
            let (u, v) = ((x as f64 + 0.5) / 48.0, 1.0 - (y as f64 + 0.5) / 48.0);
            let p = DVec3::new(2.0 * u, 0.0, 2.0 * (1.0 - v));
            // The output triangle holding it, found in 3D, and the Gouraud value there.
            let mut found = None;
            for (k, tri) in verts.triangles.iter().enumerate() {
                let f = &scene.faces[patches.face[verts.patch_of_triangle[k] as usize] as usize];
                if scene.objects[f.object as usize] != "floor" {
                    continue;
                }
                let q = tri.map(|i| verts.positions[i as usize].as_dvec3());
                let d = |a: DVec3, b: DVec3| DVec2::new(b.x - a.x, b.z - a.z);
                let area = d(q[0], q[1]).perp_dot(d(q[0], q[2]));
                let l = [
                    d(q[1], q[2]).perp_dot(d(q[1], p)) / area,
                    d(q[2], q[0]).perp_dot(d(q[2], p)) / area,
                    d(q[0], q[1]).perp_dot(d(q[0], p)) / area,
                ];
                if l.iter().all(|&w| w >= -1e-9) {
                    let rgb = tri.map(|i| verts.rgb[i as usize]);
                    found = Some(
                        (0..3)
                            .map(|c| (0..3).map(|v| l[v] * f64::from(rgb[v][c])).sum::<f64>())
                            .collect::<Vec<_>>(),
                    );
                    break;
                }
            }
            let want = found.unwrap_or_else(|| panic!("texel ({x}, {y}) at {p} is on no triangle"));
            for c in 0..3 {
                assert!(
                    (f64::from(t[c]) - want[c]).abs() <= 1e-5 * want[c].abs().max(1.0),
                    "texel ({x}, {y}) channel {c}: {} vs {}",
                    t[c],
                    want[c]
                );
            }
            checked += 1;
        }
    }
    // The floor fills the whole square: every texel is covered.
    assert_eq!(checked, 48 * 48);
    // And the full bake writes one lightmap per object.
    let cfg = BakeConfig {
        scene: dir.join("floor.obj").to_string_lossy().into_owned(),
        out_dir: dir.join("out"),
        resolution: Resolution::MaxEdge(0.3),
        preview: (16, 16),
        lightmap: Some(32),
        ..BakeConfig::default()
    };
    let s = pipeline::bake(&cfg, &Quiet).expect("bake");
    for f in ["lightmap-floor.exr", "lightmap-lamp.exr"] {
        assert!(
            s.files.contains(&dir.join("out").join(f)),
            "{f}: {:?}",
            s.files
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn faces_without_uvs_are_refused_before_any_work() {
    let dir = temp_dir("refuse");
    // The Cornell box has no UVs at all.
    let cfg = BakeConfig {
        out_dir: dir.join("out"),
        resolution: Resolution::Patches(100),
        lightmap: Some(64),
        ..BakeConfig::default()
    };
    let e = pipeline::bake(&cfg, &Quiet).unwrap_err().to_string();
    assert!(
        e.contains("--lightmap needs texture coordinates (`vt`) on every face"),
        "{e}"
    );
    assert!(!dir.join("out").exists());
    // One face of a file without them: its line and object are named.
    let obj = std::fs::read_to_string(lit_floor(&dir))
        .unwrap()
        .replace("f 5/5 6/6 7/7 8/8", "f 5/5 6 7/7 8/8");
    std::fs::write(dir.join("floor.obj"), obj).unwrap();
    let cfg = BakeConfig {
        scene: dir.join("floor.obj").to_string_lossy().into_owned(),
        ..cfg
    };
    let e = pipeline::bake(&cfg, &Quiet).unwrap_err().to_string();
    assert!(
        e.contains("floor.obj:23: a face of object `lamp` has none")
            && e.contains("1 faces of `lamp` and 1 in all"),
        "{e}"
    );
    assert!(!dir.join("out").exists());
    // From the command line, exit status 1 and nothing written.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_radiosity"))
        .args(["bake", "cornell", "--lightmap", "64", "-o"])
        .arg(dir.join("cli"))
        .output()
        .expect("binary runs");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("--lightmap needs texture coordinates"),
        "{stderr}"
    );
    assert!(!dir.join("cli").exists());
    // A size out of range.
    let e = pipeline::bake(
        &BakeConfig {
            lightmap: Some(4),
            ..cfg
        },
        &Quiet,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("between 8 and 8192"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn uvs_follow_polygons_through_their_triangulation() {
    // Two planar polygons with UVs projected from their plane (u = (x + 1) / 2,
    // v = (z + 1) / 2): a 64-corner disk, which the triangulation refines with added
    // points, and an L, which it cuts along diagonals. Every corner of every triangle,
    // added or not, must keep the projection.
    let dir = temp_dir("ngon");
    let mut obj = String::from("mtllib m.mtl\nusemtl lamp\n");
    let n = 64;
    let mut corners: Vec<(f64, f64)> = (0..n)
        .map(|k| {
            let t = std::f64::consts::TAU * k as f64 / n as f64;
            (0.9 * t.cos(), -0.9 * t.sin())
        })
        .collect();
    corners.extend(
        [
            (1.0, 0.0),
            (1.0, 0.2),
            (0.2, 0.2),
            (0.2, 1.0),
            (0.0, 1.0),
            (0.0, 0.0),
        ]
        .map(|(x, z)| (x - 1.0, z - 1.0)),
    );
    for &(x, z) in &corners {
        obj.push_str(&format!(
            "v {x} 0.5 {z}\nvt {} {}\n",
            (x + 1.0) / 2.0,
            (z + 1.0) / 2.0
        ));
    }
    obj.push('f');
    for k in 1..=n {
        obj.push_str(&format!(" {k}/{k}"));
    }
    obj.push_str("\nf");
    for k in (n + 1)..=(n + 6) {
        obj.push_str(&format!(" {k}/{k}"));
    }
    obj.push('\n');
    std::fs::write(dir.join("ngon.obj"), obj).unwrap();
    std::fs::write(dir.join("m.mtl"), "newmtl lamp\nKe 1 1 1\n").unwrap();
    let scene = Scene::load(dir.join("ngon.obj").to_str().unwrap()).expect("scene");
    assert!(
        scene.positions.len() > corners.len(),
        "the disk gained no points"
    );
    let disk_line = 3 + 2 * corners.len() as u32;
    let disk = scene.faces.iter().filter(|f| f.line == disk_line).count();
    assert!(disk > n, "{disk} triangles");
    for f in &scene.faces {
        assert!(f.has_uv());
        for (&c, &t) in f.corner_slice().iter().zip(&f.uv) {
            let p = scene.positions[c as usize];
            let uv = scene.uvs[t as usize];
            let want = DVec2::new((p.x + 1.0) / 2.0, (p.z + 1.0) / 2.0);
            assert!(
                (uv - want).length() < 1e-12,
                "line {}: {p} has {uv}, not {want}",
                f.line
            );
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}
