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
