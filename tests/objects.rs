//! The factors folder's object tables against closed forms on two-object scenes written as
//! OBJ files with two `o` objects, one of them modelled as two faces: perpendicular
//! rectangles with a common edge (Howell C-14) and directly opposed squares (C-11).

use std::path::{Path, PathBuf};

use radiosity::analytic::{parallel_rectangles, perpendicular_rectangles};
use radiosity::mesh::{PatchSet, Resolution};
use radiosity::pipeline::{self, EstimatorChoice, Quiet};
use radiosity::repair::Repair;
use radiosity::scene::Scene;
use radiosity::store;

fn temp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("radiosity-objects-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Width of the floor of [`PERPENDICULAR`] (away from the common edge) and height of its
/// wall; the common edge (the y axis) is 1 long.
const W: f64 = 2.0;
const H: f64 = 1.0;

/// The floor: `W x 1` in z = 0, facing +z, as two faces split at x = W/2; the wall: `H x 1`
/// in x = 0, facing +x.
const PERPENDICULAR: &str = "mtllib two.mtl\n\
    o the floor\nusemtl tile\n\
    v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\nv 2 1 0\n\
    f 1 2 3 4\nf 2 5 6 3\n\
    o wall\nusemtl paint\n\
    v 0 0 1\nv 0 1 1\n\
    f 1 4 8 7\n";

/// The floor: the unit square in z = 0, facing +z, as two faces split at x = 1/2; the
/// wall: the unit square in z = 1, facing -z.
const PARALLEL: &str = "mtllib two.mtl\n\
    o the floor\nusemtl tile\n\
    v 0 0 0\nv 0.5 0 0\nv 0.5 1 0\nv 0 1 0\nv 1 0 0\nv 1 1 0\n\
    f 1 2 3 4\nf 2 5 6 3\n\
    o wall\nusemtl paint\n\
    v 0 0 1\nv 1 0 1\nv 1 1 1\nv 0 1 1\n\
    f 7 10 9 8\n";

fn write_scene(dir: &Path, obj: &str) -> PathBuf {
    let mtl = "newmtl tile\nKd 0.5 0.5 0.5\nnewmtl paint\nKd 0.3 0.3 0.3\nKe 1 1 1\n";
    std::fs::write(dir.join("two.mtl"), mtl).unwrap();
    let path = dir.join("two.obj");
    std::fs::write(&path, obj).unwrap();
    path
}

/// A square table `from,NAME...` of `objects_*.csv`: the names and the rows.
fn read_table(path: &Path) -> (Vec<String>, Vec<(String, Vec<f64>)>) {
    let text = std::fs::read_to_string(path).expect("table");
    let mut lines = text.lines();
    let header: Vec<String> = lines.next().unwrap().split(',').map(String::from).collect();
    assert_eq!(header[0], "from");
    let rows = lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            let values = f[1..].iter().map(|x| x.parse().expect("number")).collect();
            (f[0].to_string(), values)
        })
        .collect();
    (header[1..].to_vec(), rows)
}

/// How close an estimate must come to the closed form.
#[derive(Clone, Copy, Debug)]
enum Within {
    /// Relative error.
    Relative(f64),
    /// Standard errors (the propagated bar).
    Bars(f64),
}

#[test]
fn object_factors_match_the_closed_form_with_their_error_bars() {
    let cases = [
        (
            "c14",
            PERPENDICULAR,
            (W, H),
            // Floor to wall, wall to floor.
            (
                perpendicular_rectangles(H, 1.0, W),
                perpendicular_rectangles(W, 1.0, H),
            ),
            // Deterministic integral for pairs nothing blocks: close to the closed form.
            EstimatorChoice::SemiAnalytic {
                points: 3,
                rays: 2,
                replicates: 4,
                tol: 1e-7,
            },
            Within::Relative(2e-4),
        ),
        (
            "c11",
            PARALLEL,
            (1.0, 1.0),
            (
                parallel_rectangles(1.0, 1.0, 1.0),
                parallel_rectangles(1.0, 1.0, 1.0),
            ),
            // Monte Carlo: within a few of its propagated standard errors.
            EstimatorChoice::AreaStratified {
                strata: 4,
                replicates: 8,
            },
            Within::Bars(4.0),
        ),
    ];
    for (tag, obj, (a_floor, a_wall), (exact_fw, exact_wf), est, within) in cases {
        assert!(
            (a_floor * exact_fw - a_wall * exact_wf).abs() < 1e-12,
            "reciprocity"
        );
        let dir = temp_dir(tag);
        let scene = write_scene(&dir, obj);
        let out = dir.join("factors");
        let s = pipeline::factors(
            scene.to_str().unwrap(),
            Resolution::Patches(150),
            &est,
            5,
            &out,
            Repair::None,
            &Quiet,
        )
        .expect("factors");
        for f in store::OBJECT_TABLES {
            assert!(
                s.provenance.sha256.contains_key(f),
                "{f} not in the provenance"
            );
        }
        let objects = std::fs::read_to_string(out.join("objects.csv")).unwrap();
        let lines: Vec<&str> = objects.lines().collect();
        assert_eq!(lines[0], "id,name,patches,area");
        for (line, (start, area)) in lines[1..]
            .iter()
            .zip([("0,the floor,", a_floor), ("1,wall,", a_wall)])
        {
            assert!(line.starts_with(start), "{line}");
            let a: f64 = line.rsplit(',').next().unwrap().parse().unwrap();
            assert!((a - area).abs() <= 1e-12, "{line}");
        }
        assert_eq!(lines.len(), 3);
        let (names, f) = read_table(&out.join("objects_F.csv"));
        let (_, se) = read_table(&out.join("objects_stderr.csv"));
        assert_eq!(names, ["the floor", "wall"]);
        assert_eq!(f[0].0, "the floor");
        let (fw, wf) = (f[0].1[1], f[1].1[0]);
        let (se_fw, se_wf) = (se[0].1[1], se[1].1[0]);
        eprintln!(
            "{tag}, {}: floor->wall {fw:.6} ± {se_fw:.1e} (exact {exact_fw:.6}), wall->floor \
             {wf:.6} ± {se_wf:.1e} (exact {exact_wf:.6})",
            s.provenance.estimator
        );
        // Coplanar faces and a flat wall see nothing of themselves.
        assert_eq!((f[0].1[0], f[1].1[1]), (0.0, 0.0));
        let ok = |got: f64, se: f64, exact: f64| match within {
            Within::Relative(r) => (got - exact).abs() <= r * exact,
            Within::Bars(k) => (got - exact).abs() <= k * se,
        };
        assert!(
            ok(fw, se_fw, exact_fw),
            "{tag}: floor->wall {fw} vs {exact_fw}"
        );
        assert!(
            ok(wf, se_wf, exact_wf),
            "{tag}: wall->floor {wf} vs {exact_wf}"
        );
        if let Within::Bars(_) = within {
            // A Monte Carlo bar is neither zero nor larger than a tenth of the value.
            assert!(se_fw > 0.0 && se_fw < 0.1 * fw, "{se_fw}");
        }
        // The stored matrix is the patch matrix aggregated: A_I F_IJ = sum A_i F_ij.
        let sc = Scene::load(scene.to_str().unwrap()).unwrap();
        let patches = PatchSet::build(&sc, Resolution::Patches(150)).unwrap();
        let ff = store::read(&out, &patches).expect("folder reads back");
        let mut s_fw = 0.0;
        for i in 0..patches.len() {
            if patches.object_name(i) == "the floor" {
                for (j, v, _) in ff.row(i) {
                    if patches.object_name(j) == "wall" {
                        s_fw += patches.area[i] * v;
                    }
                }
            }
        }
        assert!(
            (s_fw / a_floor - fw).abs() <= 1e-12,
            "{s_fw} / {a_floor} vs {fw}"
        );
        // patches.csv names each patch's object and material.
        let csv = std::fs::read_to_string(out.join("patches.csv")).unwrap();
        let mut rows = csv.lines();
        let head: Vec<&str> = rows.next().unwrap().split(',').collect();
        let (c_obj, c_mat) = (
            head.iter().position(|h| *h == "object").unwrap(),
            head.iter().position(|h| *h == "material").unwrap(),
        );
        for (i, row) in rows.enumerate() {
            let cells: Vec<&str> = row.split(',').collect();
            let want = if patches.object_name(i) == "wall" {
                ("wall", "paint")
            } else {
                ("the floor", "tile")
            };
            assert_eq!((cells[c_obj], cells[c_mat]), want, "patch {i}");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}

#[test]
fn an_edited_object_table_is_refused() {
    let dir = temp_dir("edited");
    let scene = write_scene(&dir, PERPENDICULAR);
    let out = dir.join("factors");
    let est = EstimatorChoice::AreaStratified {
        strata: 2,
        replicates: 2,
    };
    let path = scene.to_str().unwrap();
    pipeline::factors(
        path,
        Resolution::Patches(20),
        &est,
        1,
        &out,
        Repair::None,
        &Quiet,
    )
    .expect("factors");
    let sc = Scene::load(path).unwrap();
    let patches = PatchSet::build(&sc, Resolution::Patches(20)).unwrap();
    store::read(&out, &patches).expect("the folder as written reads");
    let table = out.join("objects_F.csv");
    let text = std::fs::read_to_string(&table).unwrap();
    std::fs::write(&table, text.replacen("e-1", "e-2", 1)).unwrap();
    let e = store::read(&out, &patches).unwrap_err().to_string();
    assert!(e.contains("objects_F.csv") && e.contains("SHA-256"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}
