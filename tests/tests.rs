//! Integration tests, one binary (see `Cargo.toml`, `autotests = false`).

mod bake;
mod formfactors;
mod fuzz;
mod geometry;
mod gltf;
mod hierarchy;
mod invalid;
mod lightmap;
#[cfg(feature = "mpi")]
mod mpi;
mod objects;
mod polygons;
mod reliability;
mod rows;
mod shelf;
mod stability;
mod store;
mod study;
mod suite;
mod thermal;
mod two_sided;

/// The value of the environment variable `name` (digit separators `_` allowed, as in
/// `20_000`), or `default` when it is unset or does not parse: how the long and
/// hand-run tests take their settings.
pub fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|v| v.replace('_', "").parse().ok())
        .unwrap_or(default)
}
