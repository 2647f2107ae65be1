//! Fuzzing on stable, as a test: mutated OBJ/MTL scenes through the loader and the mesher,
//! mutated Matrix Market files and provenance records through the factors-folder reader,
//! mutated npz archives (their bytes, or one member's bytes archived again) through the
//! npz reader.
//! Every run must end in a value or an error, never a panic.
//!
//! The corpus is every scene under `scenes/` and `scenes/invalid/`, the seeds under
//! `tests/fuzz/corpus/` and the factors folder `tests/fuzz/factors/`. A small mutator
//! (byte flips, insertions, deletions, repeated and swapped lines, numbers replaced by
//! extreme values, keyword lines spliced in) makes each case from a corpus file, seeded by
//! `RADIOSITY_FUZZ_SEED` (default 1) and the case number, so a failure repeats exactly. A
//! panic is caught (`catch_unwind`), and the test fails printing the case number and the
//! input that caused it.
//!
//! The CI-sized run is 20,000 loader cases, 20,000 reader cases and 5,000 npz cases; a
//! longer run sets the counts, e.g. (docs/RELIABILITY.md):
//!
//! ```text
//! RADIOSITY_FUZZ_LOADER=1000000 RADIOSITY_FUZZ_READER=100000 RADIOSITY_FUZZ_NPZ=100000 \
//!     cargo test --test tests fuzz -- --nocapture
//! ```

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};

use radiosity::mesh::{PatchSet, Resolution};
use radiosity::npz::{self, Compression};
use radiosity::scene::obj;
use radiosity::store::{self, Values};

/// SplitMix64: a small, well-mixed stream for the mutator.
struct Rng(u64);

impl Rng {
    fn new(seed: u64, case: u64) -> Rng {
        let mut r = Rng(seed ^ case.wrapping_mul(0xa076_1d64_78bd_642f));
        r.next();
        r
    }
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
    fn pick<'a, T>(&mut self, items: &'a [T]) -> &'a T {
        &items[self.below(items.len())]
    }
}

/// Numbers that break parsers and arithmetic.
const NUMBERS: &[&str] = &[
    "0",
    "-0",
    "1",
    "-1",
    "2",
    "0.5",
    "1e39",
    "-1e39",
    "3.4028235e38",
    "1e308",
    "1e-320",
    "nan",
    "inf",
    "-inf",
    "NaN",
    "4294967295",
    "4294967296",
    "18446744073709551616",
    "-2147483648",
    "9223372036854775807",
    "0x10",
    "1e",
    "",
    "1.0.0",
    "999999999",
];

/// Lines spliced into OBJ, MTL and Matrix Market text.
const LINES: &[&str] = &[
    "mtllib seed.mtl",
    "mtllib seed.mtl other.mtl",
    "mtllib missing.mtl",
    "usemtl lamp",
    "usemtl grey",
    "usemtl",
    "newmtl lamp",
    "newmtl",
    "Kd 0.99 0.99 0.99",
    "Kd 1 1 1",
    "Ke 1e38 1 1",
    "Ke 1e30 0 0",
    "v 0 0 0",
    "v 1e39 0 0",
    "v 1e-30 1e-30 1e-30",
    "v 1e30 1e30 1e30",
    "f 1 2 3",
    "f 1 2 3 4 5 6 7 8",
    "f -1 -2 -3",
    "f 1/1/1 2/2/2 3/3/3",
    "f 0 0 0",
    "vt 0 0",
    "vn 0 0 1",
    "o object",
    "g group",
    "s 1",
    "l 1 2",
    "p 1",
    "#@camera eye 0 0 5 target 0 0 0 up 0 1 0 fov 40",
    "#@camera eye 0 0 0 target 0 0 0 up 0 0 0 fov 179",
    "%%MatrixMarket matrix coordinate real symmetric",
    "% comment",
    "8 8 1000000000000000000",
    "1 1 1",
    "9 1 0.5",
    "1 1 0.5",
    "\u{feff}",
];

/// One mutation of `data`.
fn mutate_once(rng: &mut Rng, data: &mut Vec<u8>) {
    match rng.below(9) {
        0 if !data.is_empty() => {
            let k = rng.below(data.len());
            data[k] ^= 1 << rng.below(8);
        }
        1 => {
            let k = rng.below(data.len() + 1);
            data.insert(k, rng.next() as u8);
        }
        2 if !data.is_empty() => {
            let a = rng.below(data.len());
            let b = (a + 1 + rng.below(16)).min(data.len());
            data.drain(a..b);
        }
        3 => data.truncate(rng.below(data.len() + 1)),
        _ => {
            let text = String::from_utf8_lossy(data).into_owned();
            let mut lines: Vec<String> = text.lines().map(String::from).collect();
            let n = lines.len();
            match rng.below(5) {
                0 if n > 0 => {
                    let k = rng.below(n);
                    let line = lines[k].clone();
                    lines.insert(rng.below(n + 1), line);
                }
                1 if n > 1 => {
                    let (a, b) = (rng.below(n), rng.below(n));
                    lines.swap(a, b);
                }
                2 if n > 0 => {
                    // A number token replaced by an extreme value.
                    let k = rng.below(n);
                    let mut words: Vec<String> = lines[k].split(' ').map(String::from).collect();
                    let w = rng.below(words.len());
                    words[w] = rng.pick(NUMBERS).to_string();
                    lines[k] = words.join(" ");
                }
                3 if n > 0 => {
                    lines.remove(rng.below(n));
                }
                _ => lines.insert(rng.below(n + 1), rng.pick(LINES).to_string()),
            }
            *data = (lines.join("\n") + "\n").into_bytes();
        }
    }
}

/// A case: a corpus file with one to four mutations.
fn mutate(rng: &mut Rng, seed: &[u8]) -> Vec<u8> {
    let mut data = seed.to_vec();
    for _ in 0..1 + rng.below(4) {
        mutate_once(rng, &mut data);
    }
    data
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `(name, bytes)` of the files in `dirs` whose name ends with one of `exts`.
fn corpus(dirs: &[&str], exts: &[&str]) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    for dir in dirs {
        for entry in std::fs::read_dir(root().join(dir)).expect("corpus folder") {
            let path = entry.expect("entry").path();
            let name = path.file_name().unwrap().to_string_lossy().into_owned();
            if exts.iter().any(|e| name.ends_with(e)) {
                out.push((name, std::fs::read(&path).expect("corpus file")));
            }
        }
    }
    out.sort();
    assert!(!out.is_empty(), "empty corpus in {dirs:?}");
    out
}

/// Runs `cases` cases of `run` on inputs from `make`; fails on the first panic with the
/// case number and input.
fn fuzz(what: &str, cases: u64, mut make: impl FnMut(u64) -> Vec<u8>, run: impl Fn(&[u8])) {
    let mut ok = 0u64;
    let hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(|_| {}));
    let mut failure = None;
    for case in 0..cases {
        let input = make(case);
        match catch_unwind(AssertUnwindSafe(|| run(&input))) {
            Ok(()) => ok += 1,
            Err(e) => {
                let msg = e
                    .downcast_ref::<String>()
                    .cloned()
                    .or_else(|| e.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_default();
                failure = Some((case, msg, input));
                break;
            }
        }
    }
    std::panic::set_hook(hook);
    if let Some((case, msg, input)) = failure {
        panic!(
            "{what}: case {case} panicked: {msg}\ninput:\n{}",
            String::from_utf8_lossy(&input).escape_debug()
        );
    }
    eprintln!("{what}: {ok} cases, no panic");
}

#[test]
fn fuzz_the_obj_mtl_loader_and_mesher() {
    let seed = crate::env_or::<u64>("RADIOSITY_FUZZ_SEED", 1);
    let cases = crate::env_or::<u64>("RADIOSITY_FUZZ_LOADER", 20_000);
    let objs = corpus(
        &["scenes", "scenes/invalid", "tests/fuzz/corpus"],
        &[".obj"],
    );
    let mtls = corpus(
        &["scenes", "scenes/invalid", "tests/fuzz/corpus"],
        &[".mtl"],
    );
    let accepted = std::cell::Cell::new(0u64);
    let case_rng = std::cell::RefCell::new(Rng::new(seed, 0));
    fuzz(
        "loader",
        cases,
        |case| {
            let mut rng = Rng::new(seed, case);
            let base = rng.pick(&objs).1.clone();
            let obj = mutate(&mut rng, &base);
            *case_rng.borrow_mut() = rng;
            obj
        },
        |input| {
            let path = Path::new("fuzz.obj");
            let Ok(text) = radiosity::input::decode(path, input.to_vec()) else {
                return;
            };
            // Each `mtllib` gets a mutated MTL of the corpus (or none, sometimes).
            let libs = |lib: &str| -> radiosity::Result<(PathBuf, String)> {
                let mut rng = case_rng.borrow_mut();
                let p = PathBuf::from(lib);
                if rng.below(8) == 0 {
                    return Err(radiosity::Error::io(
                        &p,
                        std::io::ErrorKind::NotFound.into(),
                    ));
                }
                // The library of that name when the corpus has it, else any.
                let seed = match mtls.iter().find(|(name, _)| name == lib) {
                    Some((_, bytes)) if rng.below(4) != 0 => bytes.clone(),
                    _ => rng.pick(&mtls).1.clone(),
                };
                let bytes = if rng.below(2) == 0 {
                    seed
                } else {
                    mutate(&mut rng, &seed)
                };
                let text = radiosity::input::decode(&p, bytes)?;
                Ok((p, text))
            };
            let Ok(scene) = obj::parse("fuzz", path, &text, &libs) else {
                return;
            };
            let _ = scene.require_emitter();
            let _ = scene.camera_or_framing();
            if let Ok(patches) = PatchSet::build(&scene, Resolution::Patches(24)) {
                if patches.validate().is_ok() {
                    accepted.set(accepted.get() + 1);
                }
            }
        },
    );
    eprintln!("loader: {} scenes meshed and valid", accepted.get());
}

#[test]
fn fuzz_the_factors_folder_reader() {
    let seed = crate::env_or::<u64>("RADIOSITY_FUZZ_SEED", 1);
    let cases = crate::env_or::<u64>("RADIOSITY_FUZZ_READER", 20_000);
    let dir = root().join("tests/fuzz/factors");
    let read = |name: &str| std::fs::read(dir.join(name)).expect("corpus factors file");
    let (f, se, prov) = (read("F.mtx"), read("stderr.mtx"), read("provenance.json"));
    let n = store::parse_provenance(
        &dir.join("provenance.json"),
        &String::from_utf8_lossy(&prov),
    )
    .expect("the corpus provenance parses")
    .patches;
    let good = store::parse_mtx(
        Path::new("F.mtx"),
        &f[..],
        f.len() as u64,
        n,
        Values::FormFactors,
        None,
    )
    .expect("the corpus F.mtx parses");
    let accepted = std::cell::Cell::new(0u64);
    fuzz(
        "reader",
        cases,
        |case| {
            let mut rng = Rng::new(seed, case);
            // The first byte says which file the case is (not part of the file).
            let which = rng.below(3) as u8;
            let base = [&f, &se, &prov][which as usize];
            let mut input = vec![which];
            input.extend(mutate(&mut rng, base));
            input
        },
        |input| {
            let (which, body) = (input[0], &input[1..]);
            let len = body.len() as u64;
            let ok = match which {
                0 => store::parse_mtx(Path::new("F.mtx"), body, len, n, Values::FormFactors, None)
                    .is_ok(),
                1 => store::parse_mtx(
                    Path::new("stderr.mtx"),
                    body,
                    len,
                    n,
                    Values::StdErrors,
                    Some((&good.indptr, &good.indices)),
                )
                .is_ok(),
                _ => std::str::from_utf8(body).ok().is_some_and(|t| {
                    store::parse_provenance(Path::new("provenance.json"), t).is_ok()
                }),
            };
            if ok {
                accepted.set(accepted.get() + 1);
            }
        },
    );
    eprintln!("reader: {} cases accepted", accepted.get());
}

/// The members of a zip archive, in order.
fn unzip(bytes: &[u8]) -> Vec<(String, Vec<u8>)> {
    use std::io::Read as _;
    let mut z = zip::ZipArchive::new(std::io::Cursor::new(bytes)).expect("a zip archive");
    (0..z.len())
        .map(|k| {
            let mut f = z.by_index(k).expect("member");
            let mut v = Vec::new();
            f.read_to_end(&mut v).expect("member bytes");
            (f.name().to_string(), v)
        })
        .collect()
}

/// A stored zip archive of `members`.
fn rezip(members: &[(String, Vec<u8>)]) -> Vec<u8> {
    use std::io::Write as _;
    let mut z = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    for (name, bytes) in members {
        let opts = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Stored);
        if z.start_file(name.as_str(), opts).is_err() {
            continue; // a name the mutator made twice
        }
        z.write_all(bytes).expect("write member");
    }
    z.finish().expect("finish").into_inner()
}

#[test]
fn fuzz_the_npz_reader() {
    let seed = crate::env_or::<u64>("RADIOSITY_FUZZ_SEED", 1);
    let cases = crate::env_or::<u64>("RADIOSITY_FUZZ_NPZ", 5_000);
    let dir = root().join("tests/fuzz/factors");
    let f = std::fs::read(dir.join("F.mtx")).expect("corpus F.mtx");
    let prov = std::fs::read_to_string(dir.join("provenance.json")).expect("provenance");
    let n = store::parse_provenance(&dir.join("provenance.json"), &prov)
        .expect("the corpus provenance parses")
        .patches;
    let m = store::parse_mtx(
        Path::new("F.mtx"),
        &f[..],
        f.len() as u64,
        n,
        Values::FormFactors,
        None,
    )
    .expect("the corpus F.mtx parses");
    // The corpus matrix as npz, stored and deflated, and SciPy's own files (3 x 3).
    let tmp = std::env::temp_dir().join(format!("radiosity-fuzz-npz-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).expect("temp");
    let mut seeds: Vec<(usize, Vec<u8>)> = Vec::new();
    for c in [Compression::Stored, Compression::Deflated] {
        let p = tmp.join("F.npz");
        npz::write(&p, n, &m.indptr, &m.indices, &m.data, c).expect("write npz");
        seeds.push((n, std::fs::read(&p).expect("read npz")));
    }
    let _ = std::fs::remove_dir_all(&tmp);
    for name in ["scipy-stored.npz", "scipy-deflated.npz"] {
        seeds.push((
            3,
            std::fs::read(root().join("tests/npz").join(name)).expect("SciPy file"),
        ));
    }
    let members: Vec<Vec<(String, Vec<u8>)>> = seeds.iter().map(|(_, b)| unzip(b)).collect();
    let accepted = std::cell::Cell::new(0u64);
    fuzz(
        "npz",
        cases,
        |case| {
            let mut rng = Rng::new(seed, case);
            // The first byte says which seed (and so which n) the case is.
            let which = rng.below(seeds.len());
            let mut input = vec![which as u8];
            if rng.below(2) == 0 {
                // The archive's bytes (most changes meet a CRC or a zip header).
                input.extend(mutate(&mut rng, &seeds[which].1));
            } else {
                // One member's bytes, archived again with valid CRCs: the arrays' checks.
                let mut ms = members[which].clone();
                let k = rng.below(ms.len());
                ms[k].1 = mutate(&mut rng, &ms[k].1);
                if rng.below(8) == 0 {
                    let other = rng.below(ms.len());
                    ms.swap(k, other);
                }
                input.extend(rezip(&ms));
            }
            input
        },
        |input| {
            let (n, body) = (seeds[input[0] as usize].0, &input[1..]);
            if npz::read::<f64>(Path::new("F.npz"), body, body.len() as u64, n).is_ok() {
                accepted.set(accepted.get() + 1);
            }
        },
    );
    eprintln!("npz: {} cases accepted", accepted.get());
}
