//! The bake study: hierarchical against uniform bakes of one scene, scored against an
//! independent reference, error against CPU time and against rays.
//!
//! The reference is a table (`docs/reference/cornell-mitsuba.csv`, made by
//! `scripts/reference/mitsuba_cornell.py` with Mitsuba 3's path tracer; see
//! `docs/reference/README.md`) of face-averaged radiosities, one row per OBJ face
//! (`kind = face`, `id` its 0-based index in file order), and radiosities at probe points
//! (`kind = point`, position and normal), each with a standard error. A bake is scored the
//! way a user sees it:
//!
//! - **face averages** from the solved patches or leaves (area-weighted, buried leaves
//!   excluded), against the reference's faces;
//! - **points** from the per-vertex output mesh (the EXR/PLY values), interpolated
//!   barycentrically in the triangle that holds the point.
//!
//! Errors are relative, on Rec. 709 luminance. Each run's CPU time is the process's user
//! plus system time over the run (all threads), read from `/proc/self/stat`.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use glam::DVec3;

use crate::error::{Error, Result};
use crate::hierarchy::{self, leaves::leaf_mesh};
use crate::mesh::{PatchSet, Resolution};
use crate::output::chart::{chart, Mark, Series, Spec};
use crate::output::{interpolate, interpolate_with, write_atomic, Nodal, VertexRadiosity};
use crate::pipeline::{self, Quiet};
use crate::scene::{luminance, Scene};
use crate::solve::{Method, Options};
use crate::visibility::Visibility;

/// One reference value.
#[derive(Clone, Debug, PartialEq)]
pub struct Probe {
    /// `face` or `point`.
    pub kind: String,
    /// Face index, or the point's name.
    pub id: String,
    /// Position (points).
    pub p: DVec3,
    /// Unit normal (points).
    pub n: DVec3,
    /// Reference radiosity per channel.
    pub b: [f64; 3],
    /// Its standard error.
    pub se: [f64; 3],
    /// What the probe is for (free text: contact, shadow, control...).
    pub note: String,
}

/// Reads a reference table (see the module docs): comma-separated, a header naming at
/// least `kind,id,x,y,z,nx,ny,nz,B_r,B_g,B_b,se_r,se_g,se_b`, and optionally `note`.
pub fn read_reference(path: &Path) -> Result<Vec<Probe>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let bad = |line: usize, msg: String| Error::Output {
        path: path.to_path_buf(),
        msg: format!("line {line}: {msg}"),
    };
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let (_, header) = lines.next().ok_or_else(|| bad(1, "empty file".into()))?;
    let cols: Vec<&str> = header.split(',').map(str::trim).collect();
    let col = |name: &str| cols.iter().position(|&c| c == name);
    let need = |name: &str| col(name).ok_or_else(|| bad(1, format!("no column `{name}`")));
    let idx: Vec<usize> = [
        "x", "y", "z", "nx", "ny", "nz", "B_r", "B_g", "B_b", "se_r", "se_g", "se_b",
    ]
    .iter()
    .map(|n| need(n))
    .collect::<Result<_>>()?;
    let (kind, id, note) = (need("kind")?, need("id")?, col("note"));
    let mut out = Vec::new();
    for (k, line) in lines {
        let f: Vec<&str> = line.split(',').map(str::trim).collect();
        let num = |c: usize| -> Result<f64> {
            let v = f.get(c).copied().unwrap_or("");
            if v.is_empty() {
                return Ok(0.0);
            }
            v.parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| {
                    bad(
                        k + 1,
                        format!("`{v}` in column {} is not a number", cols[c]),
                    )
                })
        };
        let v: Vec<f64> = idx.iter().map(|&c| num(c)).collect::<Result<_>>()?;
        out.push(Probe {
            kind: f.get(kind).unwrap_or(&"").to_string(),
            id: f.get(id).unwrap_or(&"").to_string(),
            p: DVec3::new(v[0], v[1], v[2]),
            n: DVec3::new(v[3], v[4], v[5]).normalize_or_zero(),
            b: [v[6], v[7], v[8]],
            se: [v[9], v[10], v[11]],
            note: note
                .and_then(|c| f.get(c))
                .map(|s| s.to_string())
                .unwrap_or_default(),
        });
    }
    Ok(out)
}

/// The OBJ face (0-based, in file order) each scene face came from: the loader splits a
/// non-planar or larger polygon into several scene faces, all from one line.
pub fn obj_faces(scene: &Scene) -> Vec<usize> {
    let mut lines: Vec<u32> = scene.faces.iter().map(|f| f.line).collect();
    lines.sort_unstable();
    lines.dedup();
    scene
        .faces
        .iter()
        .map(|f| lines.binary_search(&f.line).unwrap_or(0))
        .collect()
}

/// Area-weighted mean radiosity of each OBJ face (index: [`obj_faces`]), from patches (or
/// leaves) `set` with values `b` and areas `areas` (for leaves, their whole areas: buried
/// ones count with their radiosity 0, as the reference's face averages do, and partly
/// buried ones with their radiosity times their exposed fraction).
pub fn face_averages(
    set: &PatchSet,
    obj_face: &[usize],
    areas: &[f64],
    b: &[[f64; 3]],
    faces: usize,
) -> Vec<Option<[f64; 3]>> {
    let mut sum = vec![[0.0; 3]; faces];
    let mut area = vec![0.0; faces];
    for (k, &f) in set.face.iter().enumerate() {
        let (f, a) = (obj_face[f as usize], areas[k]);
        if f < faces && a > 0.0 {
            for c in 0..3 {
                sum[f][c] += a * b[k][c];
            }
            area[f] += a;
        }
    }
    (0..faces)
        .map(|f| (area[f] > 0.0).then(|| sum[f].map(|s| s / area[f])))
        .collect()
}

/// The output mesh's radiosity at `p` on a surface facing `n`: barycentric interpolation
/// in the first triangle facing `n` (within 25°) whose plane passes within `tol` of `p`
/// and that holds `p`'s projection.
pub fn probe(v: &VertexRadiosity, p: DVec3, n: DVec3, tol: f64) -> Option<[f64; 3]> {
    for t in &v.triangles {
        let [a, b, c] = t.map(|k| v.positions[k as usize].as_dvec3());
        let m = (b - a).cross(c - a);
        let len = m.length();
        if len == 0.0 || m.dot(n) < 0.9 * len {
            continue;
        }
        let m = m / len;
        if m.dot(p - a).abs() > tol {
            continue;
        }
        // Barycentric coordinates of the projection.
        let q = p - m * m.dot(p - a);
        let area = len;
        let wa = (b - q).cross(c - q).dot(m) / area;
        let wb = (c - q).cross(a - q).dot(m) / area;
        let wc = 1.0 - wa - wb;
        let eps = -1e-9;
        if wa >= eps && wb >= eps && wc >= eps {
            let [ra, rb, rc] = t.map(|k| v.rgb[k as usize]);
            return Some(std::array::from_fn(|k| {
                wa * f64::from(ra[k]) + wb * f64::from(rb[k]) + wc * f64::from(rc[k])
            }));
        }
    }
    None
}

/// How a bake of the study was made.
#[derive(Clone, Debug, PartialEq)]
pub enum BakeKind {
    /// Uniform patches, the default semi-analytic factors, the default solver.
    Flat(usize),
    /// Hierarchical at this link tolerance.
    Hierarchical(f64),
}

/// One scored bake.
#[derive(Clone, Debug, PartialEq)]
pub struct Run {
    /// What was run.
    pub method: BakeKind,
    /// Patches (flat) or leaves (hierarchical).
    pub patches: usize,
    /// Links (hierarchical; 0 for flat).
    pub links: usize,
    /// Rays cast.
    pub rays: u64,
    /// CPU seconds (user + system, all threads).
    pub cpu: f64,
    /// Wall seconds.
    pub wall: f64,
    /// Largest relative error of a face average.
    pub face_max: f64,
    /// Relative error of each probe point (in reference order), `None` where no triangle
    /// held it.
    pub points: Vec<Option<f64>>,
    /// The bake's luminance at every reference row (faces and points, in order), `None`
    /// where it has none.
    pub values: Vec<Option<f64>>,
}

pub use crate::cluster::cpu_seconds;

/// Scores one bake against the reference.
#[allow(clippy::too_many_arguments)]
fn score(
    refs: &[Probe],
    obj_face: &[usize],
    set: &PatchSet,
    areas: &[f64],
    b: &[[f64; 3]],
    verts: &VertexRadiosity,
    faces: usize,
    diag: f64,
) -> (f64, Vec<Option<f64>>, Vec<Option<f64>>) {
    let avg = face_averages(set, obj_face, areas, b, faces);
    let mut face_max = 0.0f64;
    let mut points = Vec::new();
    let mut values = Vec::new();
    for r in refs {
        let want = luminance(r.b);
        if r.kind == "face" {
            let got =
                r.id.parse::<usize>()
                    .ok()
                    .and_then(|f| avg.get(f).copied().flatten());
            if let Some(got) = got {
                face_max = face_max.max((luminance(got) - want).abs() / want);
            }
            values.push(got.map(luminance));
        } else if r.kind == "point" {
            let got = probe(verts, r.p, r.n, 1e-4 * diag);
            points.push(got.map(|g| (luminance(g) - want).abs() / want));
            values.push(got.map(luminance));
        } else {
            values.push(None);
        }
    }
    (face_max, points, values)
}

/// What to run.
#[derive(Clone, Debug)]
pub struct Settings {
    /// Scene (built-in name or OBJ path).
    pub scene: String,
    /// Reference table.
    pub reference: PathBuf,
    /// Patch counts of the uniform bakes.
    pub flat: Vec<usize>,
    /// Link tolerances of the hierarchical bakes.
    pub errors: Vec<f64>,
    /// Visibility rays per side of the hierarchical links (`--link-rays`).
    pub rays: usize,
    /// Floor and cap of a receiver's radiosity in its link tolerance
    /// ([`hierarchy::Settings::relative_low`], `relative_high`).
    pub relative: (f64, f64),
    /// Share of the link tolerance above which the final gather cuts a source into its
    /// children, the floor of the receiver radiosity that cut is relative to, and the
    /// share for the leaf's view of the children ([`hierarchy::Settings::descend`],
    /// [`hierarchy::Settings::descend_low`], [`hierarchy::Settings::kernel_cut`]).
    pub descend: (f64, f64, f64),
    /// Share of a leaf's tolerance its gather's visibility noise may reach
    /// ([`hierarchy::Settings::gather_noise`]).
    pub gather_noise: f64,
    /// Split receivers whose shadows vary across them by more than the tolerance
    /// ([`hierarchy::Settings::split_shadows`]).
    pub split_shadows: bool,
    /// Seed of the hierarchical bakes' random streams ([`hierarchy::Settings::seed`]).
    pub seed: u64,
    /// Output folder.
    pub out: PathBuf,
}

impl Settings {
    /// The full study: uniform bakes of 500 to 4000 patches, hierarchical from 4% to 0.25%.
    pub fn full(out: PathBuf) -> Settings {
        Settings {
            scene: "cornell".into(),
            reference: PathBuf::from("docs/reference/cornell-mitsuba.csv"),
            flat: vec![500, 1000, 2000, 4000],
            errors: vec![0.04, 0.02, 0.01, 0.005, 0.0025],
            rays: hierarchy::Settings::default().rays,
            relative: (hierarchy::RELATIVE_LOW, hierarchy::RELATIVE_HIGH),
            descend: (
                hierarchy::DESCEND,
                hierarchy::DESCEND_LOW,
                hierarchy::KERNEL_CUT,
            ),
            gather_noise: f64::INFINITY,
            split_shadows: hierarchy::SPLIT_SHADOWS,
            seed: hierarchy::Settings::default().seed,
            out,
        }
    }
}

/// Runs the study, writes `bakes.csv` and the charts into `s.out`, and returns the runs
/// with the reference probes.
pub fn run(s: &Settings) -> Result<(Vec<Run>, Vec<Probe>)> {
    let refs = read_reference(&s.reference)?;
    let scene = Scene::load(&s.scene)?;
    let obj = obj_faces(&scene);
    let faces = obj.iter().max().map_or(0, |m| m + 1);
    let mut runs = Vec::new();
    for &n in &s.flat {
        let (c0, t0) = (cpu_seconds(), std::time::Instant::now());
        let patches = PatchSet::build(&scene, Resolution::Patches(n))?;
        let est = pipeline::BakeConfig::default().estimator;
        let (ff, _, _) = pipeline::form_factors(&patches, &est, 1, &Quiet)?;
        let (b, _) =
            pipeline::solve_radiosity(&patches, &ff, Method::default(), &Options::default())?;
        let verts = interpolate(&patches, &b, 30.0);
        let (cpu, wall) = (cpu_seconds() - c0, t0.elapsed().as_secs_f64());
        let (face_max, points, values) = score(
            &refs,
            &obj,
            &patches,
            &patches.area,
            &b,
            &verts,
            faces,
            patches.diagonal,
        );
        runs.push(Run {
            method: BakeKind::Flat(n),
            patches: patches.len(),
            links: 0,
            rays: ff.rays,
            cpu,
            wall,
            face_max,
            points,
            values,
        });
    }
    for &err in &s.errors {
        let (c0, t0) = (cpu_seconds(), std::time::Instant::now());
        let patches = PatchSet::build(&scene, Resolution::DiagonalFraction(0.25))?;
        let vis = Visibility::new(&patches)?;
        let settings = hierarchy::Settings {
            error: err,
            rays: s.rays,
            relative_low: s.relative.0,
            relative_high: s.relative.1,
            descend: s.descend.0,
            descend_low: s.descend.1,
            kernel_cut: s.descend.2,
            gather_noise: s.gather_noise,
            split_shadows: s.split_shadows,
            seed: s.seed,
            ..Default::default()
        };
        settings.validate()?;
        let sol = hierarchy::run(&patches, &vis, &settings, &|_| {})?;
        let (leaves, b, ids) = leaf_mesh(&sol.elements, &patches, &sol.state.b);
        let verts = interpolate_with(&leaves, &b, 30.0, Nodal::Linear);
        let (cpu, wall) = (cpu_seconds() - c0, t0.elapsed().as_secs_f64());
        let areas: Vec<f64> = ids.iter().map(|&l| sol.elements.area[l as usize]).collect();
        // A partly buried leaf's radiosity is that of its exposed part; the part inside the
        // solid counts with 0, as the buried leaves do.
        let b_face: Vec<[f64; 3]> = ids
            .iter()
            .zip(&b)
            .map(|(&l, v)| v.map(|x| x * sol.elements.exposed[l as usize]))
            .collect();
        let (face_max, points, values) = score(
            &refs,
            &obj,
            &leaves,
            &areas,
            &b_face,
            &verts,
            faces,
            patches.diagonal,
        );
        runs.push(Run {
            method: BakeKind::Hierarchical(err),
            patches: sol.report.leaves,
            links: sol.report.links,
            rays: sol.report.rays,
            cpu,
            wall,
            face_max,
            points,
            values,
        });
    }
    write(s, &runs, &refs)?;
    Ok((runs, refs))
}

/// The probes whose note contains `word`.
fn group<'a>(refs: &'a [Probe], word: &'a str) -> impl Iterator<Item = usize> + 'a {
    refs.iter()
        .filter(|r| r.kind == "point")
        .enumerate()
        .filter(move |(_, r)| r.note.contains(word) || r.id.contains(word))
        .map(|(k, _)| k)
}

/// Largest error over the probes of group `word` (`None` if any is missing).
pub fn group_max(run: &Run, refs: &[Probe], word: &str) -> Option<f64> {
    let mut worst = 0.0f64;
    for k in group(refs, word) {
        worst = worst.max(run.points.get(k).copied().flatten()?);
    }
    Some(worst)
}

fn label(m: &BakeKind) -> (String, String) {
    match m {
        BakeKind::Flat(n) => ("uniform".into(), format!("{n}")),
        BakeKind::Hierarchical(e) => ("hierarchical".into(), format!("{e}")),
    }
}

fn write(s: &Settings, runs: &[Run], refs: &[Probe]) -> Result<()> {
    std::fs::create_dir_all(&s.out).map_err(|e| Error::io(&s.out, e))?;
    let mut csv = String::from(
        "method,parameter,patches,links,rays,cpu_s,wall_s,face_max,contact_max,shadow_max,points_max\n",
    );
    let fmt = |x: Option<f64>| x.map_or("".into(), |v| format!("{v:.5}"));
    for r in runs {
        let (m, p) = label(&r.method);
        let all = r
            .points
            .iter()
            .flatten()
            .copied()
            .fold(None, |a: Option<f64>, b| Some(a.map_or(b, |a| a.max(b))));
        let _ = writeln!(
            csv,
            "{m},{p},{},{},{},{:.3},{:.3},{:.5},{},{},{}",
            r.patches,
            r.links,
            r.rays,
            r.cpu,
            r.wall,
            r.face_max,
            fmt(group_max(r, refs, "block-")),
            fmt(group_max(r, refs, "shadow")),
            fmt(all)
        );
    }
    let mut probes = String::from("kind,id,reference");
    for r in runs {
        let (m, p) = label(&r.method);
        let _ = write!(probes, ",{m} {p}");
    }
    probes.push('\n');
    for (k, p) in refs.iter().enumerate() {
        let _ = write!(probes, "{},{},{:.6e}", p.kind, p.id, luminance(p.b));
        for r in runs {
            let _ = write!(
                probes,
                ",{}",
                r.values
                    .get(k)
                    .copied()
                    .flatten()
                    .map_or(String::new(), |v| format!("{v:.6e}"))
            );
        }
        probes.push('\n');
    }
    let path = s.out.join("probes.csv");
    write_atomic(&path, |tmp| {
        std::fs::write(tmp, probes.as_bytes()).map_err(|e| Error::io(tmp, e))
    })?;
    let path = s.out.join("bakes.csv");
    write_atomic(&path, |tmp| {
        std::fs::write(tmp, csv.as_bytes()).map_err(|e| Error::io(tmp, e))
    })?;
    for (word, what) in [
        ("face", "worst face average"),
        ("block-", "worst point 5-15 mm from the blocks"),
        ("shadow", "worst point in the tall block's shadow"),
    ] {
        for (x_of, x_label, tag) in [(0, "CPU seconds", "cpu"), (1, "rays", "rays")] {
            let mut series = Vec::new();
            for kind in ["uniform", "hierarchical"] {
                let pts: Vec<(f64, f64)> = runs
                    .iter()
                    .filter(|r| label(&r.method).0 == kind)
                    .filter_map(|r| {
                        let y = if word == "face" {
                            Some(r.face_max)
                        } else {
                            group_max(r, refs, word)
                        }?;
                        let x = if x_of == 0 { r.cpu } else { r.rays as f64 };
                        (x > 0.0 && y > 0.0).then_some((x, y))
                    })
                    .collect();
                series.push(Series::new(kind, pts));
            }
            let title = format!("Cornell box, {what} (ref. Mitsuba 3)");
            chart(
                &s.out
                    .join(format!("{}-vs-{tag}", word.trim_end_matches('-'))),
                &Spec {
                    title: &title,
                    x_label,
                    y_label: "relative error (luminance)",
                    log_x: true,
                    // Face errors span less than a decade: a log axis would show no ticks.
                    log_y: word != "face",
                    mark: Mark::Line,
                },
                &series,
            )?;
        }
    }
    Ok(())
}
