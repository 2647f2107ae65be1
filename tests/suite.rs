//! The benchmark suite end to end: export, this program's answers through `suite run`, the
//! scorer, and a deliberately wrong matrix.

use std::path::Path;

use radiosity::mesh::Resolution;
use radiosity::pipeline::EstimatorChoice;
use radiosity::repair::Repair;
use radiosity::suite::{cases, export, run, score};

/// A fresh folder under the system's temporary folder.
fn temp_dir(tag: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("radiosity-suite-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn settings() -> run::Settings {
    run::Settings {
        resolution: Resolution::DiagonalFraction(1.0),
        estimator: EstimatorChoice::SemiAnalytic {
            points: 3,
            rays: 2,
            replicates: 4,
            tol: 1e-9,
        },
        seed: 1,
        repair: Repair::None,
    }
}

/// Patch ids of the from- and to-surfaces of a factors folder (one patch per face here).
fn ids(dir: &Path, from: &str, to: &str) -> (usize, usize) {
    let text = std::fs::read_to_string(dir.join("patches.csv")).unwrap();
    let (mut i, mut j) = (None, None);
    for line in text.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        let id: usize = f[0].parse().unwrap();
        if f[8] == from {
            i = Some(id);
        }
        if f[8] == to {
            j = Some(id);
        }
    }
    (i.unwrap(), j.unwrap())
}

#[test]
fn suite_scores_this_program_and_flags_exactly_the_perturbed_case() {
    let tmp = temp_dir("score");
    let (suite, answers) = (tmp.join("suite"), tmp.join("answers"));
    let table = export::export(&suite, &cases::all()).unwrap();
    assert!(table.cases.len() >= 40);
    let done = run::run(&suite, &answers, &settings(), &[], &mut |_| {}).unwrap();
    assert_eq!(done.len(), table.cases.len());

    let answered = score::read_folders(&answers, &table).unwrap();
    let s = score::score(&table, &answered, score::Rule::default(), "semi", "");
    eprintln!("{}", score::report(&s));
    assert_eq!(s.overall().answered, table.cases.len());
    assert!(s.flagged().is_empty(), "flagged: {:?}", s.flagged());

    // One factor of one case, 1% too large.
    let case = "cube-adjacent";
    let c = table.cases.iter().find(|c| c.case == case).unwrap();
    let dir = answers.join(case);
    let (i, j) = ids(&dir, &c.from, &c.to);
    let mtx = std::fs::read_to_string(dir.join("F.mtx")).unwrap();
    let key = format!("{} {} ", i + 1, j + 1);
    let mut hits = 0;
    let edited: String = mtx
        .lines()
        .map(|l| {
            if let Some(v) = l.strip_prefix(&key) {
                hits += 1;
                format!("{key}{:e}\n", v.parse::<f64>().unwrap() * 1.01)
            } else {
                format!("{l}\n")
            }
        })
        .collect();
    assert_eq!(hits, 1);
    std::fs::write(dir.join("F.mtx"), edited).unwrap();
    let answered = score::read_folders(&answers, &table).unwrap();
    let s = score::score(
        &table,
        &answered,
        score::Rule::default(),
        "semi, edited",
        "",
    );
    assert_eq!(s.flagged(), [case]);
    let row = s.cases.iter().find(|r| r.case == case).unwrap();
    assert!((row.relative.unwrap() - 0.01).abs() < 1e-6, "{row:?}");
}

#[test]
fn scorer_reads_csv_answers_and_names_bad_lines() {
    let tmp = temp_dir("csv");
    let suite = tmp.join("suite");
    let table = export::export(&suite, &cases::all()).unwrap();
    let c = &table.cases[0];
    let good = tmp.join("good.csv");
    std::fs::write(
        &good,
        format!(
            "case,from,to,value,stderr,seconds\n{},{},{},{},1e-3,0.5\n",
            c.case,
            c.from,
            c.to,
            c.exact * 1.002
        ),
    )
    .unwrap();
    let a = score::read_csv(&good, &table).unwrap();
    let s = score::score(&table, &a, score::Rule::default(), "csv", "");
    assert_eq!(s.overall().answered, 1);
    let row = &s.cases[0];
    assert!((row.relative.unwrap() - 0.002).abs() < 1e-9);
    assert_eq!(row.seconds, Some(0.5));
    // Within 3 bars of 1e-3: not flagged although over the tolerance.
    assert!(!row.flagged);

    for (body, line, what) in [
        ("case,from,to,value\nnope,A,B,0.1\n", 2, "no case"),
        (
            &format!("case,from,to,value\n{},{},{},x\n", c.case, c.from, c.to)[..],
            2,
            "not a number",
        ),
        (
            &format!(
                "case,from,to,value\n{0},{1},{2},0.1\n{0},{1},{2},0.1\n",
                c.case, c.from, c.to
            )[..],
            3,
            "answered again",
        ),
        ("case,value\n", 1, "lacks"),
    ] {
        let bad = tmp.join("bad.csv");
        std::fs::write(&bad, body).unwrap();
        let msg = score::read_csv(&bad, &table).unwrap_err().to_string();
        assert!(
            msg.contains(&format!("bad.csv:{line}")) && msg.contains(what),
            "{msg}"
        );
    }
}
