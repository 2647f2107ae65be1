//! The thermal mode against closed forms of radiative exchange between gray surfaces
//! (Modest, *Radiative Heat Transfer*, ch. 6; Incropera and DeWitt, ch. 13; the lecture
//! notes' cavity), with exact (semi-analytic) and Monte Carlo factors.
//!
//! Scenes: `scenes/thermal/` (written by `scripts/make_thermal_scenes.py`). Form factors
//! are computed once per scene into a factors folder and reused for every set of
//! temperatures and emissivities, as `radiosity thermal --factors DIR` does.

use std::path::{Path, PathBuf};

use exr::prelude::{ReadChannels, ReadLayers};

use radiosity::analytic::parallel_rectangles;
use radiosity::matrix::Triplets;
use radiosity::mesh::Resolution;
use radiosity::pipeline::{self, EstimatorChoice, Quiet, ThermalConfig, ThermalSummary};
use radiosity::repair::Repair;
use radiosity::scene::Boundary;
use radiosity::thermal::{
    self, reradiating_enclosure, spherical_cavity, two_surface_enclosure, Problem, Settings, SIGMA,
};

fn temp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("radiosity-thermal-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn scene(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes/thermal")
        .join(name)
        .to_string_lossy()
        .into_owned()
}

/// Whole faces as patches.
const WHOLE: Resolution = Resolution::MaxEdge(100.0);

fn exact() -> EstimatorChoice {
    EstimatorChoice::SemiAnalytic {
        points: 3,
        rays: 4,
        replicates: 4,
        tol: 1e-10,
    }
}

fn hemisphere() -> EstimatorChoice {
    EstimatorChoice::Hemisphere {
        strata: 48,
        replicates: 16,
    }
}

/// Stores the factors of `scene` once.
fn factors(
    tag: &str,
    scene: &str,
    res: Resolution,
    est: &EstimatorChoice,
    repair: Repair,
) -> PathBuf {
    let dir = temp_dir(tag);
    pipeline::factors(scene, res, est, 7, &dir, repair, &Quiet).expect("factors");
    dir
}

/// A thermal run on stored factors with the boundary conditions `rows`
/// (`material,emissivity,temperature,flux`).
fn run(
    tag: &str,
    scene: &str,
    res: Resolution,
    ff: &Path,
    rows: &str,
    zones: bool,
) -> ThermalSummary {
    let dir = temp_dir(tag);
    std::fs::create_dir_all(&dir).unwrap();
    let bc = dir.join("bc.csv");
    std::fs::write(&bc, format!("material,emissivity,temperature,flux\n{rows}")).unwrap();
    let cfg = ThermalConfig {
        scene: scene.to_string(),
        out_dir: dir.join("out"),
        resolution: res,
        factors: Some(ff.to_path_buf()),
        bc: Some(bc),
        zones,
        ..ThermalConfig::default()
    };
    let s = pipeline::thermal(&cfg, &Quiet).expect("thermal run");
    assert!(dir.join("out/patches.csv").exists() && dir.join("out/surfaces.csv").exists());
    s
}

fn flow(s: &ThermalSummary, name: &str) -> (f64, f64) {
    let x = s
        .surfaces
        .iter()
        .find(|x| x.info.name == name)
        .unwrap_or_else(|| panic!("no surface {name}"));
    (x.result.flow.q, x.result.flow.se)
}

fn area(s: &ThermalSummary, name: &str) -> f64 {
    s.surfaces
        .iter()
        .find(|x| x.info.name == name)
        .map(|x| x.result.area)
        .unwrap()
}

/// Regular icosahedron of circumradius `r`: edge `r / sin(2 pi / 5)`, area `5 sqrt 3 a²`.
fn icosahedron_area(r: f64) -> f64 {
    let a = r / (2.0 * std::f64::consts::PI / 5.0).sin();
    5.0 * 3f64.sqrt() * a * a
}

/// Emissivity and temperature pairs of the two-surface checks.
const CASES: [(f64, f64, f64, f64); 4] = [
    (0.6, 1000.0, 0.3, 300.0),
    (0.1, 800.0, 0.9, 400.0),
    (1.0, 500.0, 0.5, 1000.0),
    (0.9, 1200.0, 0.05, 0.0),
];

#[test]
fn concentric_icosahedra_two_surface_enclosure() {
    // Whole faces as patches: the icosahedral symmetry makes every inner face alike and
    // every outer face alike, so the patch solution has one radiosity per surface and the
    // two-surface closed form holds exactly. The outer-to-outer pairs can be blocked by the
    // inner body and are Monte Carlo in the semi estimator; closure (the enclosure is
    // closed) makes every outer row sum to 1, which is all the symmetric solution needs.
    let path = scene("spheres.obj");
    let ff = factors("ico-ff", &path, WHOLE, &exact(), Repair::Closure);
    let (a1, a2) = (icosahedron_area(0.5), icosahedron_area(1.0));
    for (k, &(e1, t1, e2, t2)) in CASES.iter().enumerate() {
        let rows = format!("inner,{e1},{t1},\nouter,{e2},{t2},\n");
        let s = run(&format!("ico-{k}"), &path, WHOLE, &ff, &rows, false);
        assert!((area(&s, "inner") - a1).abs() < 1e-12 * a1);
        assert!((area(&s, "outer") - a2).abs() < 1e-12 * a2);
        let want = two_surface_enclosure(a1, e1, t1, a2, e2, t2);
        let (q1, _) = flow(&s, "inner");
        let (q2, _) = flow(&s, "outer");
        eprintln!(
            "icosahedra eps {e1}/{e2}: Q1 = {q1:.10e}, closed form {want:.10e}, rel {:.1e}",
            (q1 - want) / want
        );
        assert!(((q1 - want) / want).abs() < 1e-4, "{q1} vs {want}");
        assert!(((q1 + q2) / want).abs() < 1e-9, "balance {q1} + {q2}");
    }
}

#[test]
fn zones_on_geodesic_spheres_and_coaxial_prisms() {
    // Patch by patch, the radiosity of these meshes is not uniform over a surface (the
    // geodesic spheres are not face-transitive; the prisms' caps differ from their sides),
    // so the closed form, which assumes it uniform, is what the zonal model (one zone per
    // surface) gives, exactly: F12 = 1 (convex inner body), F21 = A1/A2, F22 = 1 - A1/A2.
    for (tag, name) in [("geo", "spheres-fine.obj"), ("cyl", "cylinders.obj")] {
        let path = scene(name);
        let ff = factors(
            &format!("{tag}-ff"),
            &path,
            WHOLE,
            &exact(),
            Repair::Closure,
        );
        for (k, &(e1, t1, e2, t2)) in CASES.iter().enumerate() {
            let rows = format!("inner,{e1},{t1},\nouter,{e2},{t2},\n");
            let z = run(&format!("{tag}-z{k}"), &path, WHOLE, &ff, &rows, true);
            let (a1, a2) = (area(&z, "inner"), area(&z, "outer"));
            let want = two_surface_enclosure(a1, e1, t1, a2, e2, t2);
            let (q1, _) = flow(&z, "inner");
            let p = run(&format!("{tag}-p{k}"), &path, WHOLE, &ff, &rows, false);
            let (p1, _) = flow(&p, "inner");
            eprintln!(
                "{name} eps {e1}/{e2}: zones Q1 = {q1:.10e} (rel {:.1e}); patch by patch {p1:.10e} (rel {:.2e}); closed form {want:.10e}",
                (q1 - want) / want,
                (p1 - want) / want
            );
            assert!(((q1 - want) / want).abs() < 1e-4, "{name}: {q1} vs {want}");
            // Patch by patch the closed enclosure's flows sum to 0 within their bar (the
            // closure repair leaves reciprocity off by the shifts it makes).
            let tot = p.total.flow;
            assert!(
                tot.q.abs() <= 3.0 * tot.se + 1e-9 * want.abs(),
                "{name}: {tot:?}"
            );
            eprintln!(
                "  patch by patch: sum of Q = {:.3e} ± {:.1e} W",
                tot.q, tot.se
            );
        }
    }
    // The polyhedra's own areas: a 16-gon prism of circumradius r and length l has
    // sides 16 * 2 r sin(pi/16) * l and caps 2 * 8 r² sin(pi/8).
    let prism = |r: f64, l: f64| {
        let pi = std::f64::consts::PI;
        16.0 * 2.0 * r * (pi / 16.0).sin() * l + 16.0 * r * r * (pi / 8.0).sin()
    };
    let path = scene("cylinders.obj");
    let ff = factors("cyl-area-ff", &path, WHOLE, &exact(), Repair::Closure);
    let z = run(
        "cyl-area",
        &path,
        WHOLE,
        &ff,
        "inner,0.5,900,\nouter,0.5,300,\n",
        true,
    );
    assert!((area(&z, "inner") - prism(0.5, 10.0)).abs() < 1e-9);
    assert!((area(&z, "outer") - prism(1.0, 11.0)).abs() < 1e-9);
}

#[test]
fn opposed_plates_with_reradiating_walls() {
    // Whole faces: the four walls are alike under the square's rotations, so they share
    // one radiosity and the three-surface closed form (re-radiating surface R) is exact.
    // Every pair is unoccluded (a convex box): the semi estimator is exact to --tol.
    let path = scene("plates.obj");
    let ff = factors("plates-ff", &path, WHOLE, &exact(), Repair::None);
    let f12 = parallel_rectangles(1.0, 1.0, 0.5);
    for (k, &(e1, t1, e2, t2)) in CASES.iter().enumerate() {
        let rows = format!("plate1,{e1},{t1},\nplate2,{e2},{t2},\nwalls,0.5,,0\n");
        let s = run(&format!("plates-{k}"), &path, WHOLE, &ff, &rows, false);
        let want = reradiating_enclosure(1.0, e1, t1, 1.0, e2, t2, f12, 1.0 - f12, 1.0 - f12);
        let (q1, se1) = flow(&s, "plate1");
        let (q2, _) = flow(&s, "plate2");
        let (qw, _) = flow(&s, "walls");
        eprintln!("plates eps {e1}/{e2}: Q1 = {q1:.10e} ± {se1:.1e}, closed form {want:.10e}, rel {:.1e}; walls Q {qw:.1e}", (q1 - want) / want);
        assert!(((q1 - want) / want).abs() < 1e-4, "{q1} vs {want}");
        // Adiabatic walls carry q = 0 to the solver tolerance (1e-12 of the largest
        // |J - E_a|, at most sigma T^4 of the hottest surface).
        let scale = SIGMA * t1.max(t2).powi(4);
        assert!(
            s.adiabatic_max_q.unwrap() <= 1e-10 * scale,
            "{:?}",
            s.adiabatic_max_q
        );
        // A closed enclosure: the flows sum to 0, within their bar and to rounding.
        let tot = s.total.flow;
        assert!(tot.q.abs() <= 3.0 * tot.se + 1e-9 * want.abs(), "{tot:?}");
        assert!(((q1 + q2) / want).abs() < 1e-9);
    }
    // Finer walls: the walls' radiosity varies along them, which the closed form (one
    // re-radiating zone) ignores; the zonal model still gives it exactly.
    let fine = Resolution::MaxEdge(0.1);
    let ff = factors("plates-fine-ff", &path, fine, &exact(), Repair::None);
    let rows = "plate1,0.8,1000,\nplate2,0.4,500,\nwalls,0.5,,0\n";
    let want = reradiating_enclosure(1.0, 0.8, 1000.0, 1.0, 0.4, 500.0, f12, 1.0 - f12, 1.0 - f12);
    let z = run("plates-fine-z", &path, fine, &ff, rows, true);
    let p = run("plates-fine-p", &path, fine, &ff, rows, false);
    let (qz, _) = flow(&z, "plate1");
    let (qp, _) = flow(&p, "plate1");
    eprintln!("plates at max-edge 0.1 ({} patches): zones {qz:.10e} (rel {:.1e}), patch by patch {qp:.10e} (rel {:.2e})", p.patches, (qz - want) / want, (qp - want) / want);
    assert!(((qz - want) / want).abs() < 1e-4, "{qz} vs {want}");
    assert!(p.adiabatic_max_q.unwrap() <= 1e-10 * SIGMA * 1e12);
}

#[test]
fn reradiating_form_tends_to_infinite_plates() {
    // As the gap shrinks F12 -> 1 and the walls drop out: sigma (T1^4 - T2^4) /
    // (1/eps1 + 1/eps2 - 1) (Modest eq. 6.27).
    let (e1, e2) = (0.3, 0.7);
    let inf = SIGMA * (1000f64.powi(4) - 300f64.powi(4)) / (1.0 / e1 + 1.0 / e2 - 1.0);
    let mut last = f64::INFINITY;
    for gap in [0.1, 0.01, 0.001] {
        let f12 = parallel_rectangles(1.0, 1.0, gap);
        let q = reradiating_enclosure(1.0, e1, 1000.0, 1.0, e2, 300.0, f12, 1.0 - f12, 1.0 - f12);
        let rel = ((q - inf) / inf).abs();
        assert!(rel < last, "gap {gap}: {rel}");
        last = rel;
    }
    assert!(last < 1e-3, "{last}");
    // And with black plates and no walls' help (F12 = 1) it is the black-body exchange.
    let q = reradiating_enclosure(1.0, 1.0, 1000.0, 1.0, 1.0, 300.0, 1.0 - 1e-12, 1e-12, 1e-12);
    assert!((q / (SIGMA * (1e12 - 300f64.powi(4))) - 1.0).abs() < 1e-9);
}

#[test]
fn spherical_cavity_apparent_emissivity() {
    // The notes' cavity with the sphere's exact factors: on the inside of a sphere every
    // point sees an area element dA with factor dA / A_sphere (analytic::sphere_interior),
    // so a wall patch j, wherever it lies, receives F_ij = A_j / A_sphere from every patch
    // i (itself included). The wall is cut into unequal patches covering 1 - f of the
    // sphere; the opening (fraction f) lets radiation leave to a 0 K environment.
    let n = 37;
    for &f in &[0.01, 0.05, 0.1, 0.2, 0.35, 0.5] {
        let raw: Vec<f64> = (0..n).map(|k| 1.0 + (k % 7) as f64 * 0.3).collect();
        let sum: f64 = raw.iter().sum();
        let a_sphere = 4.0 * std::f64::consts::PI;
        let area: Vec<f64> = raw.iter().map(|a| a / sum * (1.0 - f) * a_sphere).collect();
        let mut t = Triplets::new((n, n));
        for i in 0..n {
            for (j, &aj) in area.iter().enumerate() {
                t.add_triplet(i, j, radiosity::analytic::sphere_interior(aj, a_sphere));
            }
        }
        let fm = t.to_csr();
        let se = vec![0.0; fm.nnz()];
        for k in 1..=9 {
            let eps = k as f64 / 10.0;
            let temp = 1000.0;
            let p = Problem {
                f: &fm,
                se: &se,
                area: &area,
                emissivity: &vec![eps; n],
                boundary: &vec![Boundary::Temperature(temp); n],
                ambient: 0.0,
            };
            let sol = thermal::solve(&p, &Settings::default()).unwrap();
            let q: f64 = (0..n).map(|i| area[i] * sol.q[i]).sum();
            // The opening's plane disk has area A_o = f A_wall (A_wall F_wall,o = A_o).
            let a_wall: f64 = area.iter().sum();
            let apparent = q / (f * a_wall * SIGMA * temp.powi(4));
            let want = spherical_cavity(eps, f);
            assert!(
                ((apparent - want) / want).abs() < 1e-4,
                "eps {eps}, f {f}: {apparent} vs {want}"
            );
            assert!((sol.to_environment - q).abs() < 1e-9 * q);
        }
    }
}

#[test]
fn monte_carlo_factors_within_their_bars() {
    // Hemisphere factors (rows independent; bars calibrated at shared edges, see
    // docs/ESTIMATORS.md) with a fixed seed. Each check is |error| <= K bars; with 9 checks
    // (8 closed-form comparisons, correlated through the shared factors, and the balance)
    // a family false-alarm rate of 1e-3 needs two-sided 1.1e-4 per check: 3.9 normal
    // standard errors, and K = 5 for bars estimated from 16 replicates (t, 15 degrees of
    // freedom, where 3.9 becomes about 5). The check fails for an error bar that is too
    // small or a biased solve.
    const K: f64 = 5.0;
    let path = scene("plates.obj");
    let ff = factors("mc-plates-ff", &path, WHOLE, &hemisphere(), Repair::None);
    let f12 = parallel_rectangles(1.0, 1.0, 0.5);
    let mut worst: f64 = 0.0;
    for (k, &(e1, t1, e2, t2)) in CASES.iter().enumerate() {
        let rows = format!("plate1,{e1},{t1},\nplate2,{e2},{t2},\nwalls,0.5,,0\n");
        let s = run(&format!("mc-plates-{k}"), &path, WHOLE, &ff, &rows, false);
        let want = reradiating_enclosure(1.0, e1, t1, 1.0, e2, t2, f12, 1.0 - f12, 1.0 - f12);
        let (q1, se1) = flow(&s, "plate1");
        let z = (q1 - want) / se1;
        eprintln!("hemisphere plates eps {e1}/{e2}: Q1 = {q1:.6e} ± {se1:.1e}, closed form {want:.6e}: {z:+.2} bars ({:.1e} relative)", (q1 - want) / want);
        assert!(se1 > 0.0 && z.abs() <= K, "{z} bars");
        worst = worst.max(z.abs());
        // The closed enclosure's balance.
        let tot = s.total.flow;
        assert!(tot.q.abs() <= K * tot.se, "sum of Q {tot:?}");
    }
    let path = scene("spheres.obj");
    let ff = factors("mc-ico-ff", &path, WHOLE, &hemisphere(), Repair::None);
    let (a1, a2) = (icosahedron_area(0.5), icosahedron_area(1.0));
    for (k, &(e1, t1, e2, t2)) in CASES.iter().enumerate() {
        let rows = format!("inner,{e1},{t1},\nouter,{e2},{t2},\n");
        let s = run(&format!("mc-ico-{k}"), &path, WHOLE, &ff, &rows, false);
        let want = two_surface_enclosure(a1, e1, t1, a2, e2, t2);
        let (q1, se1) = flow(&s, "inner");
        let z = (q1 - want) / se1;
        eprintln!("hemisphere icosahedra eps {e1}/{e2}: Q1 = {q1:.6e} ± {se1:.1e}, closed form {want:.6e}: {z:+.2} bars ({:.1e} relative)", (q1 - want) / want);
        assert!(se1 > 0.0 && z.abs() <= K, "{z} bars");
        worst = worst.max(z.abs());
    }
    eprintln!("worst |error| / bar: {worst:.2}");
}

#[test]
fn bad_thermal_input_is_refused_before_work() {
    let dir = temp_dir("bad");
    std::fs::create_dir_all(&dir).unwrap();
    let bc = dir.join("bc.csv");
    std::fs::write(
        &bc,
        "material,emissivity,temperature,flux\nplate1,0.8,1000,\nnone,0.5,300,\n",
    )
    .unwrap();
    let cfg = ThermalConfig {
        scene: scene("plates.obj"),
        out_dir: dir.join("out"),
        bc: Some(bc.clone()),
        ..ThermalConfig::default()
    };
    let e = pipeline::thermal(&cfg, &Quiet).unwrap_err().to_string();
    assert!(
        e.contains("bc.csv:3") && e.contains("no material `none`"),
        "{e}"
    );
    assert!(!dir.join("out").exists());
    // A scene whose materials have no thermal properties names the material.
    let cfg = ThermalConfig {
        scene: "cornell".into(),
        out_dir: dir.join("out"),
        ..ThermalConfig::default()
    };
    let e = pipeline::thermal(&cfg, &Quiet).unwrap_err().to_string();
    assert!(e.contains("has no thermal properties"), "{e}");
    let cfg = ThermalConfig {
        scene: scene("plates.obj"),
        out_dir: dir.join("out"),
        ambient: f64::NAN,
        ..ThermalConfig::default()
    };
    assert!(pipeline::thermal(&cfg, &Quiet).is_err());
    // Adiabatic plates and walls only: no temperature anywhere in a closed box.
    std::fs::write(
        &bc,
        "material,emissivity,flux\nplate1,0.8,0\nplate2,0.8,0\n",
    )
    .unwrap();
    let cfg = ThermalConfig {
        scene: scene("plates.obj"),
        out_dir: dir.join("out"),
        resolution: WHOLE,
        bc: Some(bc),
        ..ThermalConfig::default()
    };
    let e = pipeline::thermal(&cfg, &Quiet).unwrap_err().to_string();
    assert!(e.contains("singular"), "{e}");
    assert!(!dir.join("out").exists());
}

/// `patches.csv` of a thermal run: per row, the surface and the named columns.
fn read_patches_csv(path: &Path, columns: &[&str]) -> Vec<(String, Vec<f64>)> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let at: Vec<usize> = columns
        .iter()
        .map(|c| head.iter().position(|h| h == c).unwrap())
        .collect();
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (
                f[1].to_string(),
                at.iter().map(|&k| f[k].parse().unwrap()).collect(),
            )
        })
        .collect()
}

#[test]
fn per_vertex_exr_and_ply_agree_with_patches_csv() {
    // The plates box split into patches 0.25 across: the plates (given temperatures) carry
    // their temperature at every vertex; the walls' vertices average their patches.
    let path = scene("plates.obj");
    let res = Resolution::MaxEdge(0.25);
    let ff = factors("vertex-ff", &path, res, &exact(), Repair::None);
    let rows = "plate1,0.8,1000,\nplate2,0.4,500,\nwalls,0.5,,0\n";
    let s = run("vertex", &path, res, &ff, rows, false);
    let out = s.files[0].parent().unwrap().to_path_buf();
    for f in ["thermal.exr", "mesh.ply"] {
        assert!(s.files.contains(&out.join(f)), "{:?}", s.files);
    }
    let manifest = std::fs::read_to_string(out.join("manifest.json")).unwrap();
    assert!(manifest.contains("thermal.exr") && manifest.contains("mesh.ply"));

    // EXR channel, patches.csv column.
    let pairs = [
        ("T_K", "T_K"),
        ("T_se", "T_se"),
        ("J_W_m2", "J_W_m2"),
        ("J_se", "J_se"),
        ("G_W_m2", "G_W_m2"),
        ("G_se", "G_se"),
        ("q_W_m2", "q_W_m2"),
        ("q_se", "q_se"),
    ];
    let cols: Vec<&str> = pairs.iter().map(|p| p.1).collect();
    let table = read_patches_csv(&out.join("patches.csv"), &cols);
    assert_eq!(table.len(), s.patches);

    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_file(out.join("thermal.exr"))
        .unwrap();
    let layer = &image.layer_data;
    let attr = |name: &str| {
        layer
            .attributes
            .other
            .iter()
            .find(|(k, _)| *k == name)
            .map(|(_, v)| v.clone())
            .unwrap_or_else(|| panic!("no attribute {name}"))
    };
    let n = match attr("radiosity:vertexCount") {
        exr::meta::attribute::AttributeValue::I32(n) => n as usize,
        v => panic!("{v:?}"),
    };
    match attr("radiosity:layout") {
        exr::meta::attribute::AttributeValue::Text(t) => {
            assert!(
                t.to_string().starts_with("radiosity-thermal-vertex/1"),
                "{t}"
            )
        }
        v => panic!("{v:?}"),
    }
    let names: Vec<String> = layer
        .channel_data
        .list
        .iter()
        .map(|c| c.name.to_string())
        .collect();
    assert!(
        !names.iter().any(|c| ["R", "G", "B"].contains(&c.as_str())),
        "{names:?}"
    );
    let channel = |name: &str| -> Vec<f32> {
        let c = layer
            .channel_data
            .list
            .iter()
            .find(|c| c.name.to_string() == name)
            .unwrap_or_else(|| panic!("no channel {name} in {names:?}"));
        c.sample_data.values_as_f32().take(n).collect()
    };
    let (px, py, pz) = (channel("P.x"), channel("P.y"), channel("P.z"));
    let ny = channel("N.y");
    let values: Vec<Vec<f32>> = pairs.iter().map(|p| channel(p.0)).collect();
    assert!(n > 8 && values.iter().all(|v| v.len() == n));

    // A vertex's surface from its position and normal (plate1 at y = 0, plate2 at y = 0.5).
    let surface_of = |k: usize| {
        if ny[k].abs() > 0.99 && py[k] == 0.0 {
            "plate1"
        } else if ny[k].abs() > 0.99 && py[k] == 0.5 {
            "plate2"
        } else {
            "walls"
        }
    };
    let mut seen = [0usize; 3];
    for (k, &t_k) in values[0].iter().enumerate() {
        let surface = surface_of(k);
        let given = match surface {
            "plate1" => Some(1000.0f32),
            "plate2" => Some(500.0f32),
            _ => None,
        };
        seen[["plate1", "plate2", "walls"]
            .iter()
            .position(|s| *s == surface)
            .unwrap()] += 1;
        if let Some(t) = given {
            assert_eq!(t_k, t, "vertex {k} of {surface}");
        }
        // Every value is an average of its surface's patch values: within their range.
        for (c, (name, _)) in pairs.iter().enumerate() {
            let (lo, hi) = table
                .iter()
                .filter(|(s, _)| s == surface)
                .map(|(_, v)| v[c])
                .fold((f64::MAX, f64::MIN), |(l, h), x| (l.min(x), h.max(x)));
            let x = f64::from(values[c][k]);
            let slack = 1e-6 * lo.abs().max(hi.abs()) + 1e-9;
            assert!(
                x >= lo - slack && x <= hi + slack,
                "vertex {k} ({surface}) {name} = {x} outside [{lo}, {hi}]"
            );
        }
    }
    assert!(seen.iter().all(|&c| c > 0), "{seen:?}");
    // patches.csv holds the given temperatures exactly too.
    for (surface, t) in [("plate1", 1000.0), ("plate2", 500.0)] {
        assert!(table.iter().filter(|r| r.0 == surface).all(|r| r.1[0] == t));
    }

    // mesh.ply: header, then the same vertices as the EXR.
    let bytes = std::fs::read(out.join("mesh.ply")).unwrap();
    let end = b"end_header\n";
    let at = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
    let head = std::str::from_utf8(&bytes[..at]).unwrap();
    let lines: Vec<&str> = head.lines().collect();
    assert_eq!(lines[1], "format binary_little_endian 1.0");
    assert!(
        lines.contains(&format!("element vertex {n}").as_str()),
        "{head}"
    );
    let comment = lines.iter().find(|l| l.starts_with("comment ")).unwrap();
    assert!(
        comment.contains(" K") && comment.contains("W/m2"),
        "{comment}"
    );
    let props: Vec<&str> = lines
        .iter()
        .filter_map(|l| l.strip_prefix("property "))
        .collect();
    assert_eq!(
        props[..12],
        [
            "float x",
            "float y",
            "float z",
            "float nx",
            "float ny",
            "float nz",
            "uchar red",
            "uchar green",
            "uchar blue",
            "float temperature",
            "float flux",
            "float quality"
        ]
    );
    let size = 6 * 4 + 3 + 3 * 4;
    let body = &bytes[at..];
    let f32_at = |o: usize| f32::from_le_bytes(body[o..o + 4].try_into().unwrap());
    let (t_lo, t_hi) = values[0]
        .iter()
        .fold((f32::MAX, f32::MIN), |(l, h), &x| (l.min(x), h.max(x)));
    assert_eq!((t_lo, t_hi), (500.0, 1000.0));
    for k in 0..n {
        let v = k * size;
        assert_eq!(
            [f32_at(v), f32_at(v + 4), f32_at(v + 8)],
            [px[k], py[k], pz[k]]
        );
        let (t, q, quality) = (f32_at(v + 27), f32_at(v + 31), f32_at(v + 35));
        assert_eq!(t.to_bits(), values[0][k].to_bits(), "temperature {k}");
        assert_eq!(q.to_bits(), values[6][k].to_bits(), "flux {k}");
        assert_eq!(quality.to_bits(), t.to_bits(), "quality {k}");
        let colour = &body[v + 24..v + 27];
        if t == t_hi {
            assert_eq!(colour, [252, 255, 164], "hottest vertex {k}");
        } else if t == t_lo {
            assert_eq!(colour, [0, 0, 4], "coldest vertex {k}");
        }
    }
}

#[test]
fn npz_factors_give_the_thermal_solution_text_factors_give() {
    let path = scene("plates.obj");
    let mut flows = Vec::new();
    for (format, tag) in [
        (radiosity::store::Format::Mtx, "fmt-mtx"),
        (radiosity::store::Format::Npz, "fmt-npz"),
    ] {
        let dir = temp_dir(tag);
        pipeline::factors_within(
            &path,
            WHOLE,
            &exact(),
            7,
            &dir,
            Repair::None,
            format,
            None,
            false,
            &Quiet,
        )
        .expect("factors");
        let rows = "plate1,0.8,1000,\nplate2,0.4,500,\nwalls,0.5,,0\n";
        let s = run(&format!("{tag}-run"), &path, WHOLE, &dir, rows, false);
        flows.push(["plate1", "plate2", "walls"].map(|name| flow(&s, name)));
    }
    assert_eq!(
        flows[0], flows[1],
        "the same factors, the same flows to the bit"
    );
}
