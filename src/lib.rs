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
pub mod error;
pub mod formfactor;
pub mod matrix;
pub mod mesh;
pub mod output;
pub mod pipeline;
pub mod repair;
pub mod sampling;
pub mod scene;
pub mod simd;
pub mod solve;
pub mod store;
pub mod study;
pub mod visibility;

pub use error::{Error, Result};
