//! # radiosity
//!
//! Monte Carlo radiosity form factors on Embree 4, radiosity solvers, and per-vertex
//! radiosity baked into OpenEXR.
//!
//! The pipeline, one module per stage, data flowing one way:
//!
//! `Scene` ([`scene`]) → `PatchSet` ([`mesh`]) → `FormFactors` ([`formfactor`] over
//! [`visibility`], assembled by [`matrix`]) → radiosity ([`solve`]) → per-vertex values and
//! files ([`output`]); [`pipeline`] is the only place that knows the order and times it.
//! Stored factors ([`store`]) carry the matrix aggregated over the scene's named objects
//! ([`objects`]).
//! The hierarchical path branches after the mesh: root patches → element tree and links
//! refined where the light needs them, solved on the tree ([`hierarchy`], over
//! [`visibility`] and the exact integral of [`formfactor::exact`]) → the leaves as a
//! crack-free mesh → the same per-vertex values and files.
//! The thermal mode ([`thermal`]) takes the same `FormFactors` with per-material
//! emissivities and temperatures or net fluxes, and solves the net-radiation method for
//! radiosity, irradiation, net heat flux and temperature, with propagated error bars.
//!
//! ## No import cycles
//! The modules form an acyclic graph: a module refers only to modules upstream of it
//! (`error`, `cluster`, `input`, `budget`, `scene`, `mesh`, `sampling`, `simd`, `visibility`,
//! `analytic`, `matrix`, `formfactor`, `hierarchy`, `repair`, `solve`, `thermal`, `output`,
//! `objects`, `npz`, `store`, `pipeline`, then the consumers `study`, `suite` and `bench`, and
//! `mpi`, the MPI implementation of [`cluster::Cluster`], built only with the cargo
//! feature `mpi`). The test
//! `tests::module_graph_is_acyclic` at
//! the bottom of this file checks it: it reads every file under `src/`, takes each
//! `crate::MODULE` path in the code before the file's `#[cfg(test)]` (comments and doc
//! links aside), and fails naming a cycle if there is one; `cargo test --lib module_graph`
//! prints the graph.
//!
//! ## Glossary (fixed meanings of names in code and docs)
//! - `i`, `j`: patch indices; `x`, `y`: points on patches i and j; `n_x`, `n_y`: their normals.
//! - `r2`: squared distance `|y - x|²`; `cos_x`, `cos_y`: cosines at each end.
//! - `f_ij` / `F_ij`: form factor from i to j, the fraction of energy leaving i that reaches j.
//! - `rho`: diffuse reflectance in [0, 1); `emit` / `E`: emitted exitance; `b` / `B`: radiosity.
//! - The radiosity system: `B = E + diag(rho) F B` (radiosidade.md, "Sistema Linear").
#![deny(unsafe_code)]
#![warn(missing_docs)]

pub mod analytic;
pub mod bench;
pub mod budget;
pub mod cluster;
pub mod error;
pub mod formfactor;
pub mod hierarchy;
pub mod input;
pub mod matrix;
pub mod mesh;
#[cfg(feature = "mpi")]
pub mod mpi;
pub mod npz;
pub mod objects;
pub mod output;
pub mod pipeline;
pub mod repair;
pub mod sampling;
pub mod scene;
pub mod simd;
pub mod solve;
pub mod store;
pub mod study;
pub mod suite;
pub mod thermal;
pub mod visibility;

pub use error::{Error, Result};

#[cfg(test)]
mod tests {
    use std::collections::{BTreeMap, BTreeSet};
    use std::path::Path;

    /// Top-level module of a file under `src/` (`formfactor/semi.rs` -> `formfactor`).
    fn module_of(rel: &Path) -> String {
        let first = rel
            .components()
            .next()
            .unwrap()
            .as_os_str()
            .to_string_lossy();
        first.trim_end_matches(".rs").to_string()
    }

    /// The modules a file's code (before its `#[cfg(test)]`, outside comments) names as
    /// `crate::MODULE`.
    fn references(text: &str) -> BTreeSet<String> {
        let mut out = BTreeSet::new();
        for line in text.lines() {
            let code = line.trim_start();
            if code.starts_with("#[cfg(test)]") {
                break;
            }
            let code = code.split("//").next().unwrap_or("");
            let mut rest = code;
            while let Some(k) = rest.find("crate::") {
                rest = &rest[k + "crate::".len()..];
                let name: String = rest
                    .chars()
                    .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                    .collect();
                if !name.is_empty() {
                    out.insert(name);
                }
            }
        }
        out
    }

    fn walk(dir: &Path, root: &Path, graph: &mut BTreeMap<String, BTreeSet<String>>) {
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                walk(&path, root, graph);
            } else if path.extension().is_some_and(|e| e == "rs") {
                let rel = path.strip_prefix(root).unwrap();
                let module = module_of(rel);
                // The crate root, and the binary's own modules (they use the library by
                // its name, never `crate::`).
                if module == "lib" || module == "main" || module == "cli" {
                    continue;
                }
                let text = std::fs::read_to_string(&path).unwrap();
                let refs = graph.entry(module.clone()).or_default();
                refs.extend(references(&text).into_iter().filter(|m| *m != module));
            }
        }
    }

    /// Depth-first search; returns a cycle as a path of module names, if there is one.
    fn cycle(graph: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
        fn visit(
            m: &str,
            graph: &BTreeMap<String, BTreeSet<String>>,
            state: &mut BTreeMap<String, u8>,
            path: &mut Vec<String>,
        ) -> Option<Vec<String>> {
            match state.get(m) {
                Some(2) => return None,
                Some(1) => {
                    let at = path.iter().position(|p| p == m).unwrap();
                    let mut c = path[at..].to_vec();
                    c.push(m.to_string());
                    return Some(c);
                }
                _ => {}
            }
            state.insert(m.to_string(), 1);
            path.push(m.to_string());
            for next in graph.get(m).into_iter().flatten() {
                if let Some(c) = visit(next, graph, state, path) {
                    return Some(c);
                }
            }
            path.pop();
            state.insert(m.to_string(), 2);
            None
        }
        let mut state = BTreeMap::new();
        for m in graph.keys() {
            if let Some(c) = visit(m, graph, &mut state, &mut Vec::new()) {
                return Some(c);
            }
        }
        None
    }

    #[test]
    fn cycle_finder_finds_cycles() {
        let g = |edges: &[(&str, &str)]| {
            let mut g: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
            for (a, b) in edges {
                g.entry(a.to_string()).or_default().insert(b.to_string());
            }
            g
        };
        assert!(cycle(&g(&[("a", "b"), ("b", "c"), ("a", "c")])).is_none());
        let c = cycle(&g(&[("a", "b"), ("b", "c"), ("c", "a")])).unwrap();
        assert_eq!(c.len(), 4, "{c:?}");
        let refs = references("use crate::mesh::X; // crate::solve\n#[cfg(test)]\nuse crate::io;");
        assert_eq!(refs.into_iter().collect::<Vec<_>>(), ["mesh"]);
    }

    #[test]
    fn module_graph_is_acyclic() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
        let mut graph = BTreeMap::new();
        walk(&root, &root, &mut graph);
        for (m, refs) in &graph {
            eprintln!(
                "{m} -> {}",
                refs.iter().cloned().collect::<Vec<_>>().join(", ")
            );
        }
        assert!(graph.len() > 10, "{graph:?}");
        if let Some(c) = cycle(&graph) {
            panic!("import cycle: {}", c.join(" -> "));
        }
    }
}
