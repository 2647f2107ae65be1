//! Radiosity solvers for (I - diag(rho) F) B = E.
