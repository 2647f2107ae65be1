//! Radiative heat transfer between opaque gray diffuse surfaces: the net-radiation method
//! on the patches' form-factor matrix, with error bars propagated from the factors' own.
//!
//! ## The equations
//! Every patch `i` has an emissivity `eps_i` in (0, 1] (Kirchhoff: absorptance `eps_i`,
//! reflectance `1 - eps_i`; radiosidade.md, "Emissividade", "Lei de Kirchhoff") and either a
//! temperature `T_i` or a net flux `q_i` (W/m², leaving the surface). Radiation that leaves
//! the scene (`1 - sum_j F_ij` of what patch i sends) reaches a black environment at the
//! ambient temperature `T_a`, which sends back the same share. With the radiosity `J`
//! (emitted plus reflected, W/m²) and the irradiation `G` (arriving, W/m²), the
//! net-radiation method (Hottel; Modest, *Radiative Heat Transfer*, 3rd ed., sec. 6.3,
//! eqs. 6.20-6.23; Siegel and Howell, *Thermal Radiation Heat Transfer*, ch. 5) reads
//!
//! ```text
//! G_i = sum_j F_ij J_j + (1 - sum_j F_ij) E_a,          E_a = sigma T_a^4
//! q_i = J_i - G_i                                         (net flux, both conditions)
//! J_i = eps_i sigma T_i^4 + (1 - eps_i) G_i               (temperature given)
//! J_i = G_i + q_i                                         (flux given)
//! ```
//!
//! In `u = J - E_a` both conditions are one linear system,
//!
//! ```text
//! u_i - r_i sum_j F_ij u_j = b_i,    r_i = 1 - eps_i, b_i = eps_i (sigma T_i^4 - E_a)   (temperature)
//!                                    r_i = 1,         b_i = q_i                          (flux)
//! ```
//!
//! `M u = b` with `M = I - diag(r) F`: the visible-light system `B = E + diag(rho) F B` with
//! `rho = r` and `E = b`. A flux patch reflects all it receives (`r = 1`), which the
//! visible-light solvers refuse on purpose ([`crate::solve::System`] requires `rho < 1`: in a
//! closed scene lit only by such patches the system is singular). So this module solves it
//! with its own over-relaxed Gauss–Seidel iteration (the visible-light solver's factor,
//! [`crate::solve::Sor`]), after checking that it is not singular: every patch
//! must reach, through the non-zero entries of `F`, an absorbing patch (a given temperature)
//! or a leak to the environment ([`Error::Singular`] otherwise, naming a patch). `M` is then
//! a non-singular M-matrix (`diag(r) F >= 0` with spectral radius below 1), for which
//! Gauss–Seidel converges, for `M` and for its transpose alike (Varga, *Matrix Iterative
//! Analysis*, thm. 3.15), and which a factor that does not pay falls back to. Rows with `r_i sum_j F_ij >= 1` (Monte Carlo noise on flux patches
//! of a closed scene) are first scaled to sum to 1, as the bake does
//! ([`crate::matrix::repair_row_sums`]), with a note.
//!
//! `q = J - G` is computed as `u_i - (F u)_i` for every patch (for a temperature patch it
//! equals `eps/(1 - eps) (sigma T^4 - J)`, Modest eq. 6.22, which has no limit at eps = 1);
//! the temperature of a flux patch follows from `J = eps sigma T^4 + (1 - eps) G`:
//! `sigma T^4 = J + (1 - eps)/eps q`. A flux no temperature can produce (it would need
//! `sigma T^4 < 0`) is refused, naming the patch. Stefan–Boltzmann constant: [`SIGMA`]
//! (CODATA 2018, exact in the SI).
//!
//! ## Error bars
//! The factors carry standard errors `s_ij` (their estimators' replicates, or a quadrature's
//! error estimate). Two entries of one pair that satisfy reciprocity to rounding,
//! `A_i F_ij = A_j F_ji` with `A_i s_ij = A_j s_ji` (the semi-analytic and area estimators
//! compute each pair once and fill the other entry by reciprocity; so does the reciprocity
//! repair), are one random variable; all other entries are taken as independent (hemisphere
//! rows: independent between rows; within a row their multinomial covariance is negative and
//! is left out, which overestimates the variance of any combination of non-negative
//! radiosities). The propagation is first order (linearised), in two ways:
//!
//! - **Surface totals** `Q_S = sum_{i in S} A_i q_i` (and the total over the scene): exactly,
//!   by one adjoint solve each. With `dM = -diag(r) dF`, `M du = diag(r) dF u`, so
//!   `dQ_S = sum_ij h_i u_j dF_ij` with `h_i = r_i lambda_i - A_i [i in S]` and
//!   `M^T lambda = (I - F)^T (A 1_S)`; the variance is the sum over the random variables of
//!   their sensitivity squared times `s²`, and entries whose error is deterministic (a
//!   bound `b`, [`crate::matrix::Bar`]) add `|sensitivity| b` to a separate bound, linearly
//!   ([`surfaces`], [`linear_se`]; [`Flow::bound`]).
//! - **Per patch** (`J`, `G`, `q`, `T`): by `K` random tangent solves
//!   ([`Settings::replicates`]): draw `dF` with the entries' standard errors (normal, pairs
//!   shared as above), solve `M du = diag(r) dF u`, and take the root mean square of the
//!   resulting changes. These bars are themselves estimates, with a relative spread of about
//!   `1 / sqrt(2K)` (18% for the default 16). A bounded entry is drawn here with its bound
//!   as if a standard error ([`crate::matrix::Bar::magnitude`]): these per-patch bars are
//!   standard errors, and the bounds (1e-6 of a factor by default) are small beside them.
//!
//! Neither includes the solver's own error, which its tolerance bounds (the default,
//! `1e-12` of the largest `|J - E_a|`, is far below any factor's error bar).
//!
//! ## Energy balance
//! With reciprocal factors `sum_i A_i q_i = sum_j A_j (1 - sum_k F_jk)(J_j - E_a)`, the net
//! power that leaves to the environment ([`Solution::to_environment`]); in a closed
//! enclosure both are 0 up to the factors' errors (rows summing to 1 within their bars).
//!
//! Optional wavebands (per-band emissivities, e.g. solar and infrared) are not implemented:
//! every surface is gray over the whole spectrum.

pub mod bc;

use crate::error::{Error, Result};
use crate::matrix::{reciprocal_pairs, Bar, Csr};
use crate::sampling::Pcg32;
use crate::scene::Boundary;
use crate::solve::gauss_seidel::{relaxation, Adaptive};

/// Stefan–Boltzmann constant, W m^-2 K^-4 (CODATA 2018; exact since the 2019 SI).
pub const SIGMA: f64 = 5.670374419e-8;

/// Black-body emissive power `sigma T^4`, W/m².
pub fn emissive_power(t: f64) -> f64 {
    SIGMA * t.powi(4)
}

/// A thermal problem on a patch set: borrowed arrays, one entry per patch (and the
/// factors' standard errors aligned with `f.data()`).
#[derive(Clone, Copy, Debug)]
pub struct Problem<'a> {
    /// `F[i, j]`, by rows (CSR).
    pub f: &'a Csr,
    /// Error bar of each stored factor, aligned with `f.data()`, in its stored form
    /// ([`Bar::of`]: a standard error, or a bound).
    pub se: &'a [f32],
    /// Patch areas, m² (or the scene's units squared: fluxes are per unit area).
    pub area: &'a [f64],
    /// Emissivity per patch, in (0, 1].
    pub emissivity: &'a [f64],
    /// Boundary condition per patch.
    pub boundary: &'a [Boundary],
    /// Ambient (environment) temperature, K.
    pub ambient: f64,
}

/// Solver settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Settings {
    /// Stop when every row's residual is at most this times the largest `|J - E_a|` (and
    /// `|b|`).
    pub tolerance: f64,
    /// Cap on sweeps per solve.
    pub max_iterations: usize,
    /// Random tangent solves for the per-patch error bars (0: no per-patch bars).
    pub replicates: usize,
    /// Seed of their random perturbations.
    pub seed: u64,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            tolerance: 1e-12,
            max_iterations: 100_000,
            replicates: 16,
            seed: 1,
        }
    }
}

/// The solution, per patch, with standard errors from the factors' error bars.
#[derive(Clone, Debug)]
pub struct Solution {
    /// Radiosity `J`, W/m².
    pub j: Vec<f64>,
    /// Irradiation `G`, W/m².
    pub g: Vec<f64>,
    /// Net flux leaving `q = J - G`, W/m².
    pub q: Vec<f64>,
    /// Temperature, K (given, or solved for on flux patches).
    pub t: Vec<f64>,
    /// Standard errors of `j`, `g`, `q`, `t` (per-patch tangent replicates; all 0 when
    /// `replicates` is 0).
    pub se_j: Vec<f64>,
    /// See `se_j`.
    pub se_g: Vec<f64>,
    /// See `se_j`.
    pub se_q: Vec<f64>,
    /// See `se_j`.
    pub se_t: Vec<f64>,
    /// Net power to the environment, `sum_j A_j (1 - sum_k F_jk)(J_j - E_a)`, W.
    pub to_environment: f64,
    /// Its standard error (tangent replicates).
    pub se_to_environment: f64,
    /// Sweeps of the main solve (over-relaxed Gauss–Seidel).
    pub iterations: usize,
    /// Largest row residual of the main solve relative to its scale.
    pub residual: f64,
    /// Warnings (rows scaled, singular-looking systems).
    pub notes: Vec<String>,
    /// The unknown `u = J - E_a`.
    u: Vec<f64>,
    /// `r_i` of the system.
    r: Vec<f64>,
    /// The factors the solve used (rows repaired as in the module docs).
    f: Csr,
}

impl Solution {
    /// The solution of a zone problem ([`crate::objects::lump`]) carried to the patches: patch i gets the
    /// values of zone `zone[i]`.
    pub fn spread(&self, zone: &[u32]) -> Solution {
        let pick = |v: &[f64]| zone.iter().map(|&z| v[z as usize]).collect::<Vec<f64>>();
        Solution {
            j: pick(&self.j),
            g: pick(&self.g),
            q: pick(&self.q),
            t: pick(&self.t),
            se_j: pick(&self.se_j),
            se_g: pick(&self.se_g),
            se_q: pick(&self.se_q),
            se_t: pick(&self.se_t),
            u: pick(&self.u),
            r: pick(&self.r),
            notes: self.notes.clone(),
            f: self.f.clone(),
            ..*self
        }
    }
}

/// Net heat flow of a surface (a set of patches): `Q = sum A_i q_i` and its propagated
/// standard error.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Flow {
    /// Net power leaving the surface, W.
    pub q: f64,
    /// Its first-order standard error from the factors' standard errors (adjoint), W.
    pub se: f64,
    /// Its first-order bound from the factors' bounds (adjoint, added linearly), W.
    pub bound: f64,
}

impl Problem<'_> {
    /// Number of patches.
    pub fn len(&self) -> usize {
        self.area.len()
    }

    /// True when there are no patches.
    pub fn is_empty(&self) -> bool {
        self.area.is_empty()
    }

    /// Checks lengths and ranges.
    pub fn validate(&self) -> Result<()> {
        let n = self.area.len();
        let f = self.f;
        if f.rows() != n || f.cols() != n || !f.is_csr() {
            return Err(Error::Config(format!(
                "the form-factor matrix is {}x{} (CSR: {}) for {n} patches",
                f.rows(),
                f.cols(),
                f.is_csr()
            )));
        }
        if self.se.len() != f.nnz() || self.emissivity.len() != n || self.boundary.len() != n {
            return Err(Error::Config(format!(
                "{} standard errors for {} factors, {} emissivities and {} boundary \
                 conditions for {n} patches",
                self.se.len(),
                f.nnz(),
                self.emissivity.len(),
                self.boundary.len()
            )));
        }
        if let Some(k) = f.data().iter().position(|v| !(v.is_finite() && *v >= 0.0)) {
            return Err(Error::Config(format!(
                "stored factor {k} is {}, not a finite number >= 0",
                f.data()[k]
            )));
        }
        if let Some(k) = self.se.iter().position(|&v| !Bar::of(v).is_valid()) {
            return Err(Error::Config(format!(
                "error bar {k} is {}, not a finite number >= 0",
                Bar::of(self.se[k])
            )));
        }
        for i in 0..n {
            if !(self.area[i].is_finite() && self.area[i] > 0.0) {
                return Err(Error::Config(format!("patch {i}: area {}", self.area[i])));
            }
            let t = crate::scene::Thermal {
                emissivity: self.emissivity[i],
                boundary: self.boundary[i],
            };
            t.validate()
                .map_err(|m| Error::Config(format!("patch {i}: {m}")))?;
        }
        if !(self.ambient.is_finite()
            && (0.0..=crate::scene::MAX_TEMPERATURE).contains(&self.ambient))
        {
            return Err(Error::Config(format!(
                "ambient temperature {} K is outside [0, {:e}] K",
                self.ambient,
                crate::scene::MAX_TEMPERATURE
            )));
        }
        Ok(())
    }

    /// `r_i` and `b_i` of the linear system (module docs).
    fn system(&self) -> (Vec<f64>, Vec<f64>) {
        let ea = emissive_power(self.ambient);
        self.boundary
            .iter()
            .zip(self.emissivity)
            .map(|(bc, &eps)| match *bc {
                Boundary::Temperature(t) => (1.0 - eps, eps * (emissive_power(t) - ea)),
                Boundary::Flux(q) => (1.0, q),
            })
            .unzip()
    }
}

/// Row sums of a CSR matrix.
fn row_sums(f: &Csr) -> Vec<f64> {
    f.outer_iterator().map(|r| r.data().iter().sum()).collect()
}

/// `F x`.
fn mul(f: &Csr, x: &[f64]) -> Vec<f64> {
    f.outer_iterator()
        .map(|r| r.iter().map(|(j, v)| v * x[j]).sum())
        .collect()
}

/// Successive over-relaxation for `x - diag(r) A x = b` (`A >= 0` by rows, `diag(r) A` of
/// spectral radius below 1), from `x`, with the visible-light solver's factor
/// ([`crate::solve::Sor`]: the proven one from `max_i r_i sum_j A_ij`, which is Gauss–Seidel
/// when that reaches 1 as with flux patches, then Young's for the rate the sweeps show,
/// falling back on the first if it does not pay); stops when every row's residual is at
/// most `tol` times the largest of `|x|` and `|b|`. Returns the sweeps and the final
/// relative residual.
fn gauss_seidel(
    a: &Csr,
    r: &[f64],
    b: &[f64],
    x: &mut [f64],
    tol: f64,
    max_iterations: usize,
    what: &str,
) -> Result<(usize, f64)> {
    let n = b.len();
    let residual = |x: &[f64]| -> f64 {
        let ax = mul(a, x);
        let worst = (0..n)
            .map(|i| (b[i] + r[i] * ax[i] - x[i]).abs())
            .fold(0.0, f64::max);
        let scale = x.iter().chain(b).map(|v| v.abs()).fold(0.0, f64::max);
        if scale == 0.0 {
            0.0
        } else {
            worst / scale
        }
    };
    let gain = (0..n)
        .map(|i| {
            let row = a.outer_view(i).expect("row in range");
            r[i] * row.iter().map(|(_, v)| v.abs()).sum::<f64>()
        })
        .fold(0.0, f64::max);
    let mut factor = Adaptive::new(relaxation(gain));
    let mut res = residual(x);
    let first = res.max(f64::MIN_POSITIVE);
    for k in 0..=max_iterations {
        if !res.is_finite() || res > 1e12 * first.max(1.0) {
            return Err(Error::Singular {
                solver: format!("thermal sor ({what})"),
                msg: format!(
                    "the iteration diverges (relative residual {res:.3e} after {k} sweeps): \
                     rows of F sum so far above 1 that diag(1 - eps) F has spectral radius 1 \
                     or more"
                ),
            });
        }
        if res <= tol {
            return Ok((k, res));
        }
        if k == max_iterations {
            break;
        }
        let omega = factor.omega();
        for i in 0..n {
            let row = a.outer_view(i).expect("row in range");
            let (mut off, mut aii) = (0.0, 0.0);
            for (j, v) in row.iter() {
                if j == i {
                    aii += v;
                } else {
                    off += v * x[j];
                }
            }
            let gs = (b[i] + r[i] * off) / (1.0 - r[i] * aii);
            x[i] += omega * (gs - x[i]);
        }
        res = residual(x);
        factor.observe(res);
    }
    Err(Error::NotConverged {
        solver: format!("thermal sor ({what})"),
        iterations: max_iterations,
        residual: res,
        tolerance: tol,
        hint: "; raise --max-iterations or --tolerance (the system is close to singular: \
               nearly closed regions bounded by flux-given or low-emissivity surfaces)"
            .into(),
    })
}

/// Scales rows with `r_i sum_j F_ij >= 1` to sum to 1 (module docs).
fn repaired(f: &Csr, r: &[f64], notes: &mut Vec<String>) -> Csr {
    let rho: Vec<[f64; 3]> = r.iter().map(|&v| [v; 3]).collect();
    match crate::matrix::repair_row_sums(f, &rho) {
        Some((g, rep)) => {
            let changed = rep
                .rows
                .iter()
                .filter(|&&i| {
                    let s: f64 = f.outer_view(i).map_or(0.0, |r| r.data().iter().sum());
                    (s - 1.0).abs() > 1e-15
                })
                .count();
            if changed > 0 {
                notes.push(format!(
                    "{changed} rows of F on flux-given or reflecting patches summed to at \
                     least 1/(1 - eps) (worst {:.6} at patch {}) and were scaled to sum to 1",
                    rep.worst.1, rep.worst.0
                ));
            }
            g
        }
        None => f.clone(),
    }
}

/// Refuses a singular system: every patch must reach an absorbing patch (`r < 1`) or a
/// leak to the environment through the non-zero entries of `F` (module docs).
fn check_grounded(p: &Problem, f: &Csr, r: &[f64]) -> Result<()> {
    let n = p.len();
    let ptr = f.indptr();
    let ptr = ptr.to_proper();
    let sums = row_sums(f);
    let mut grounded = vec![false; n];
    let mut stack = Vec::new();
    for i in 0..n {
        let bar = crate::matrix::sum_bar(&p.se[ptr[i]..ptr[i + 1]]);
        if r[i] < 1.0 || 1.0 - sums[i] > bar.allowance(3.0).max(1e-9) {
            grounded[i] = true;
            stack.push(i);
        }
    }
    let ft = f.transpose_view().to_csr();
    while let Some(j) = stack.pop() {
        if let Some(col) = ft.outer_view(j) {
            for (i, v) in col.iter() {
                if *v > 0.0 && !grounded[i] {
                    grounded[i] = true;
                    stack.push(i);
                }
            }
        }
    }
    match grounded.iter().position(|g| !g) {
        None => Ok(()),
        Some(i) => Err(Error::Singular {
            solver: "thermal".into(),
            msg: format!(
                "patch {i} (and {} more) sees only patches with a given net flux, in a region \
             closed to the environment: their radiosities and temperatures are not \
             determined (the net-radiation system is singular); give some surface there a \
             temperature",
                grounded.iter().filter(|g| !**g).count() - 1
            ),
        }),
    }
}

/// A standard normal draw (Box–Muller).
fn normal(rng: &mut Pcg32) -> f64 {
    let u1 = 1.0 - rng.next_f64();
    let u2 = rng.next_f64();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// Solves the net-radiation problem (module docs), with per-patch error bars from
/// `settings.replicates` tangent solves.
pub fn solve(p: &Problem, settings: &Settings) -> Result<Solution> {
    p.validate()?;
    if !(settings.tolerance.is_finite() && settings.tolerance > 0.0 && settings.tolerance < 1.0) {
        return Err(Error::Config(format!(
            "thermal solver tolerance {} is not in (0, 1)",
            settings.tolerance
        )));
    }
    let n = p.len();
    let (r, b) = p.system();
    let mut notes = Vec::new();
    let f = repaired(p.f, &r, &mut notes);
    check_grounded(p, &f, &r)?;
    let mut u = b.clone();
    let (iterations, residual) = gauss_seidel(
        &f,
        &r,
        &b,
        &mut u,
        settings.tolerance,
        settings.max_iterations,
        "radiosity",
    )?;
    let ea = emissive_power(p.ambient);
    let fu = mul(&f, &u);
    let q: Vec<f64> = (0..n).map(|i| u[i] - fu[i]).collect();
    let j: Vec<f64> = u.iter().map(|v| v + ea).collect();
    let g: Vec<f64> = (0..n).map(|i| j[i] - q[i]).collect();
    let mut t = vec![0.0; n];
    for i in 0..n {
        t[i] = match p.boundary[i] {
            Boundary::Temperature(t) => t,
            Boundary::Flux(qi) => {
                let eps = p.emissivity[i];
                let eb = j[i] + (1.0 - eps) / eps * qi;
                if eb < 0.0 {
                    return Err(Error::Config(format!(
                        "patch {i}: a net flux of {qi} W/m^2 cannot leave it: with \
                         emissivity {eps} and irradiation G = {:.6e} W/m^2 that would need a \
                         negative black-body emission sigma T^4 = {eb:.6e}",
                        g[i]
                    )));
                }
                (eb / SIGMA).powf(0.25)
            }
        };
    }
    let sums = row_sums(&f);
    let to_environment = (0..n).map(|i| p.area[i] * (1.0 - sums[i]) * u[i]).sum();
    let mut sol = Solution {
        se_j: vec![0.0; n],
        se_g: vec![0.0; n],
        se_q: vec![0.0; n],
        se_t: vec![0.0; n],
        j,
        g,
        q,
        t,
        to_environment,
        se_to_environment: 0.0,
        iterations,
        residual,
        notes,
        u,
        r,
        f,
    };
    tangent_replicates(p, settings, &mut sol)?;
    Ok(sol)
}

/// Per-patch standard errors by random tangent solves (module docs).
fn tangent_replicates(p: &Problem, settings: &Settings, sol: &mut Solution) -> Result<()> {
    let k = settings.replicates;
    if k == 0 {
        return Ok(());
    }
    let n = p.len();
    let f = &sol.f;
    // The repaired matrix has the pattern of the original: the same positions for `se`.
    let pairs = reciprocal_pairs(p.f, p.se, p.area);
    let ptr = f.indptr();
    let ptr = ptr.to_proper();
    let ind = f.indices();
    let mut acc = [vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n]];
    let mut env2 = 0.0;
    let mut df = vec![0.0; f.nnz()];
    for rep in 0..k {
        let mut rng = Pcg32::keyed(settings.seed, 0x007e_57a1, rep as u64, 0);
        for i in 0..n {
            for e in ptr[i]..ptr[i + 1] {
                let jj = ind[e] as usize;
                match pairs[e] {
                    // The pair's variable is drawn at its lower-row entry; the mirror
                    // follows by reciprocity.
                    Some(m) if jj < i => df[e] = df[m] * p.area[jj] / p.area[i],
                    _ => df[e] = Bar::of(p.se[e]).magnitude() * normal(&mut rng),
                }
            }
        }
        // dF u, and the right-hand side diag(r) dF u.
        let mut dfu = vec![0.0; n];
        for i in 0..n {
            dfu[i] = (ptr[i]..ptr[i + 1])
                .map(|e| df[e] * sol.u[ind[e] as usize])
                .sum();
        }
        let rhs: Vec<f64> = (0..n).map(|i| sol.r[i] * dfu[i]).collect();
        let mut du = vec![0.0; n];
        gauss_seidel(
            f,
            &sol.r,
            &rhs,
            &mut du,
            settings.tolerance,
            settings.max_iterations,
            "error bars",
        )?;
        let fdu = mul(f, &du);
        let mut denv = 0.0;
        for i in 0..n {
            let dq = du[i] - fdu[i] - dfu[i];
            let dj = du[i];
            let dg = dj - dq;
            let dt = match p.boundary[i] {
                Boundary::Temperature(_) => 0.0,
                Boundary::Flux(_) if sol.t[i] > 0.0 => dj / (4.0 * SIGMA * sol.t[i].powi(3)),
                Boundary::Flux(_) => 0.0,
            };
            for (a, d) in acc.iter_mut().zip([dj, dg, dq, dt]) {
                a[i] += d * d;
            }
            let s: f64 = (ptr[i]..ptr[i + 1]).map(|e| f.data()[e]).sum();
            let ds: f64 = (ptr[i]..ptr[i + 1]).map(|e| df[e]).sum();
            denv += p.area[i] * ((1.0 - s) * du[i] - ds * sol.u[i]);
        }
        env2 += denv * denv;
    }
    let rms = |v: &[f64]| v.iter().map(|s| (s / k as f64).sqrt()).collect::<Vec<_>>();
    sol.se_j = rms(&acc[0]);
    sol.se_g = rms(&acc[1]);
    sol.se_q = rms(&acc[2]);
    sol.se_t = rms(&acc[3]);
    sol.se_to_environment = (env2 / k as f64).sqrt();
    Ok(())
}

/// The first-order bar of a quantity `y` with `dy = a . du + d . (dF u)`, by one adjoint
/// solve `M^T lambda = a`: `dy = sum_ij h_i u_j dF_ij` with `h = diag(r) lambda + d`
/// (module docs), summed over the random variables of `F` (reciprocal pairs coupled): the
/// standard errors in quadrature, the bounds linearly.
pub fn linear_se(
    p: &Problem,
    sol: &Solution,
    a: &[f64],
    d: &[f64],
    settings: &Settings,
) -> Result<Bar> {
    let n = p.len();
    let f = &sol.f;
    // M^T = I - F^T diag(r): Gauss–Seidel on x - 1 (F^T diag(r)) x = a.
    let mut ftr = f.transpose_view().to_csr();
    let cols = ftr.indices().to_vec();
    for (v, &j) in ftr.data_mut().iter_mut().zip(&cols) {
        *v *= sol.r[j as usize];
    }
    let mut lambda = a.to_vec();
    gauss_seidel(
        &ftr,
        &vec![1.0; n],
        a,
        &mut lambda,
        settings.tolerance,
        settings.max_iterations,
        "adjoint",
    )?;
    let h: Vec<f64> = (0..n).map(|i| sol.r[i] * lambda[i] + d[i]).collect();
    let pairs = reciprocal_pairs(p.f, p.se, p.area);
    let ptr = f.indptr();
    let ptr = ptr.to_proper();
    let ind = f.indices();
    let (mut var, mut bound) = (0.0, 0.0);
    for i in 0..n {
        for e in ptr[i]..ptr[i + 1] {
            let j = ind[e] as usize;
            let g = h[i] * sol.u[j];
            let bar = Bar::of(p.se[e]);
            let g = match pairs[e] {
                // Counted with its mirror, at the entry above the diagonal.
                Some(_) if j < i => continue,
                Some(_) => g + h[j] * sol.u[i] * p.area[i] / p.area[j],
                None => g,
            };
            var += g * g * bar.se * bar.se;
            bound += g.abs() * bar.bound;
        }
    }
    Ok(Bar {
        se: var.sqrt(),
        bound,
    })
}

/// What a surface (a set of patches) does: net heat flow and mean temperature with their
/// first-order standard errors.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SurfaceResult {
    /// Net heat flow leaving the surface, `Q = sum A_i q_i`.
    pub flow: Flow,
    /// Area-weighted mean temperature, K.
    pub t: f64,
    /// Its standard error (0 on a surface of given temperature), K.
    pub se_t: f64,
    /// Area.
    pub area: f64,
    /// Area-weighted mean radiosity and irradiation, W/m².
    pub j: f64,
    /// See `j`.
    pub g: f64,
}

/// Net heat flow and mean temperature of each surface, `group[i]` naming patch i's surface
/// (`0..groups`), and of the whole scene (the last entry), with first-order standard errors
/// by adjoint solves ([`linear_se`]): for `Q_S`, `a = (I - F)^T (A 1_S)` and `d = -A 1_S`;
/// for the mean temperature, `a_i = A_i / (A_S 4 sigma T_i^3)` on flux patches and `d = 0`.
pub fn surfaces(
    p: &Problem,
    sol: &Solution,
    group: &[u32],
    groups: usize,
    settings: &Settings,
) -> Result<Vec<SurfaceResult>> {
    let n = p.len();
    if group.len() != n || group.iter().any(|&g| g as usize >= groups) {
        return Err(Error::Config(format!(
            "{} surface labels for {n} patches, or one past {groups} surfaces",
            group.len()
        )));
    }
    let ft = sol.f.transpose_view().to_csr();
    let mut out = Vec::with_capacity(groups + 1);
    for s in 0..=groups {
        let member = |i: usize| s == groups || group[i] as usize == s;
        let a1: Vec<f64> = (0..n)
            .map(|i| if member(i) { p.area[i] } else { 0.0 })
            .collect();
        let area: f64 = a1.iter().sum();
        let mean =
            |x: &[f64]| (0..n).map(|i| a1[i] * x[i]).sum::<f64>() / area.max(f64::MIN_POSITIVE);
        let q: f64 = (0..n).map(|i| a1[i] * sol.q[i]).sum();
        let fta = mul(&ft, &a1);
        let w: Vec<f64> = (0..n).map(|i| a1[i] - fta[i]).collect();
        let d: Vec<f64> = a1.iter().map(|v| -v).collect();
        let bar = linear_se(p, sol, &w, &d, settings)?;
        let c: Vec<f64> = (0..n)
            .map(|i| match p.boundary[i] {
                Boundary::Flux(_) if sol.t[i] > 0.0 => {
                    a1[i] / (area * 4.0 * SIGMA * sol.t[i].powi(3))
                }
                _ => 0.0,
            })
            .collect();
        let se_t = if c.iter().any(|&v| v != 0.0) {
            linear_se(p, sol, &c, &vec![0.0; n], settings)?.magnitude()
        } else {
            0.0
        };
        out.push(SurfaceResult {
            flow: Flow {
                q,
                se: bar.se,
                bound: bar.bound,
            },
            t: mean(&sol.t),
            se_t,
            area,
            j: mean(&sol.j),
            g: mean(&sol.g),
        });
    }
    Ok(out)
}

/// The two-surface enclosure's closed form: net heat flow from surface 1 (area `a1`,
/// emissivity `eps1`, temperature `t1`) to the surface enclosing it (`a2`, `eps2`, `t2`)
/// when surface 1 sees only surface 2 (`F12 = 1`, so `F21 = A1/A2`, `F22 = 1 - A1/A2`):
/// `Q1 = sigma A1 (T1^4 - T2^4) / (1/eps1 + (A1/A2)(1/eps2 - 1))` (Modest, 3rd ed.,
/// eq. 6.26 and example 6.3; Incropera and DeWitt, *Fundamentals of Heat and Mass
/// Transfer*, 6th ed., eq. 13.25 and table 13.3). Exact for two isothermal surfaces of
/// uniform radiosity.
pub fn two_surface_enclosure(a1: f64, eps1: f64, t1: f64, a2: f64, eps2: f64, t2: f64) -> f64 {
    SIGMA * a1 * (t1.powi(4) - t2.powi(4)) / (1.0 / eps1 + a1 / a2 * (1.0 / eps2 - 1.0))
}

/// Two isothermal surfaces exchanging heat directly and through a re-radiating
/// (adiabatic) third surface R: `Q1 = sigma A1 (T1^4 - T2^4) / ((1 - eps1)/eps1 + 1/Fbar +
/// (A1/A2)(1 - eps2)/eps2)`, `Fbar = F12 + 1/(1/F1R + A1/(A2 F2R))` (the network of Oppenheim
/// 1956 solved for `J_R`: Incropera and DeWitt, 6th ed., eq. 13.30; Modest, 3rd ed., sec.
/// 6.3; Holman, *Heat Transfer*, eq. 8-41). Exact for three surfaces of uniform radiosity.
#[allow(clippy::too_many_arguments)]
pub fn reradiating_enclosure(
    a1: f64,
    eps1: f64,
    t1: f64,
    a2: f64,
    eps2: f64,
    t2: f64,
    f12: f64,
    f1r: f64,
    f2r: f64,
) -> f64 {
    let fbar = f12 + 1.0 / (1.0 / f1r + a1 / (a2 * f2r));
    SIGMA * a1 * (t1.powi(4) - t2.powi(4))
        / ((1.0 - eps1) / eps1 + 1.0 / fbar + a1 / a2 * (1.0 - eps2) / eps2)
}

/// Apparent emissivity of an isothermal diffuse spherical cavity of wall emissivity `eps`
/// whose opening takes the fraction `f` of the sphere's area: `eps / (eps + (1 - eps) f)`
/// (radiosidade.md, "Cavidade"; Siegel and Howell, sec. 6.4; exact for the sphere, where
/// every wall point sees the opening with factor `f`). The opening's power is
/// `eps_a sigma T^4 A_o` with `A_o = f A_wall` the area of the opening's plane disk
/// (`A_wall F_wall,o = A_o`).
pub fn spherical_cavity(eps: f64, f: f64) -> f64 {
    eps / (eps + (1.0 - eps) * f)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::matrix::Triplets;

    fn csr(n: usize, entries: &[(usize, usize, f64)]) -> Csr {
        let mut t = Triplets::new((n, n));
        for &(i, j, v) in entries {
            t.add_triplet(i, j, v);
        }
        t.to_csr()
    }

    /// Two infinite parallel plates as two unit patches seeing only each other: the
    /// textbook `q = sigma (T1^4 - T2^4) / (1/eps1 + 1/eps2 - 1)` (Modest eq. 6.27).
    #[test]
    fn parallel_plates() {
        let f = csr(2, &[(0, 1, 1.0), (1, 0, 1.0)]);
        let se = [0.0, 0.0];
        let bc = [Boundary::Temperature(1000.0), Boundary::Temperature(300.0)];
        for (e1, e2) in [(0.2, 0.7), (1.0, 0.5), (1.0, 1.0), (0.05, 0.05)] {
            let p = Problem {
                f: &f,
                se: &se,
                area: &[1.0, 1.0],
                emissivity: &[e1, e2],
                boundary: &bc,
                ambient: 0.0,
            };
            let sol = solve(&p, &Settings::default()).unwrap();
            let exact = SIGMA * (1000f64.powi(4) - 300f64.powi(4)) / (1.0 / e1 + 1.0 / e2 - 1.0);
            assert!(
                (sol.q[0] - exact).abs() < 1e-9 * exact,
                "{} {exact}",
                sol.q[0]
            );
            assert!((sol.q[1] + exact).abs() < 1e-9 * exact);
            assert!(sol.to_environment.abs() < 1e-9 * exact);
        }
    }

    /// A plate facing black space at T_a: q = eps sigma (T^4 - T_a^4); a flux patch in the
    /// same place reaches the temperature that radiates its flux.
    #[test]
    fn open_plate_and_flux_temperature() {
        let f = csr(1, &[]);
        let p = Problem {
            f: &f,
            se: &[],
            area: &[2.0],
            emissivity: &[0.4],
            boundary: &[Boundary::Temperature(500.0)],
            ambient: 250.0,
        };
        let sol = solve(&p, &Settings::default()).unwrap();
        let exact = 0.4 * SIGMA * (500f64.powi(4) - 250f64.powi(4));
        assert!((sol.q[0] - exact).abs() < 1e-9 * exact);
        assert!((sol.g[0] - emissive_power(250.0)).abs() < 1e-9);
        assert!((sol.to_environment - 2.0 * exact).abs() < 1e-9 * exact);
        let p = Problem {
            boundary: &[Boundary::Flux(exact)],
            ..p
        };
        let sol = solve(&p, &Settings::default()).unwrap();
        assert!((sol.t[0] - 500.0).abs() < 1e-9, "{}", sol.t[0]);
    }

    /// Only flux-given patches in a closed pair: refused as singular, naming a patch.
    #[test]
    fn closed_flux_only_is_refused() {
        let f = csr(2, &[(0, 1, 1.0), (1, 0, 1.0)]);
        let p = Problem {
            f: &f,
            se: &[0.0, 0.0],
            area: &[1.0, 1.0],
            emissivity: &[0.5, 0.5],
            boundary: &[Boundary::Flux(10.0), Boundary::Flux(-10.0)],
            ambient: 0.0,
        };
        let e = solve(&p, &Settings::default()).unwrap_err().to_string();
        assert!(e.contains("patch 0") && e.contains("singular"), "{e}");
        // Impossible flux: extracting heat from a patch in 0 K space.
        let f = csr(1, &[]);
        let p = Problem {
            f: &f,
            se: &[],
            area: &[1.0],
            emissivity: &[0.5],
            boundary: &[Boundary::Flux(-1.0)],
            ambient: 0.0,
        };
        let e = solve(&p, &Settings::default()).unwrap_err().to_string();
        assert!(e.contains("negative black-body"), "{e}");
    }

    /// The adjoint bar of a surface total agrees with the tangent replicates' spread of
    /// the same total, and with a finite-difference derivative.
    #[test]
    fn adjoint_bars_match_replicates_and_differences() {
        // Three patches: a hot plate, a cold plate and an adiabatic wall, open a little.
        let e = [
            (0, 1, 0.3),
            (0, 2, 0.6),
            (1, 0, 0.3),
            (1, 2, 0.6),
            (2, 0, 0.3),
            (2, 1, 0.3),
            (2, 2, 0.2),
        ];
        let f = csr(3, &e);
        let se = vec![0.01; 7];
        let bc = [
            Boundary::Temperature(800.0),
            Boundary::Temperature(400.0),
            Boundary::Flux(0.0),
        ];
        let p = Problem {
            f: &f,
            se: &se,
            area: &[1.0, 1.0, 1.0],
            emissivity: &[0.6, 0.8, 0.5],
            boundary: &bc,
            ambient: 300.0,
        };
        let settings = Settings {
            replicates: 4000,
            ..Settings::default()
        };
        let sol = solve(&p, &settings).unwrap();
        assert!(sol.q[2].abs() < 1e-9 * sol.q[0].abs(), "{:?}", sol.q);
        let flows: Vec<Flow> = surfaces(&p, &sol, &[0, 1, 2], 3, &settings)
            .unwrap()
            .iter()
            .map(|s| s.flow)
            .collect();
        // Patch 0's flow: its adjoint bar against the replicates' bar of q_0 (area 1),
        // whose relative spread is 1/sqrt(2 * 4000) = 1.1%.
        let rel = flows[0].se / sol.se_q[0];
        assert!(
            (rel - 1.0).abs() < 0.05,
            "{} vs {}",
            flows[0].se,
            sol.se_q[0]
        );
        // The adiabatic wall's temperature bar, adjoint against replicates.
        let t = surfaces(&p, &sol, &[0, 1, 2], 3, &settings).unwrap()[2];
        assert!(
            (t.se_t / sol.se_t[2] - 1.0).abs() < 0.05,
            "{} {}",
            t.se_t,
            sol.se_t[2]
        );
        // Entries (0,1) and (1,0) are reciprocal (equal areas and values): one random
        // variable; the others are independent. The same variance by finite differences.
        let pairs = reciprocal_pairs(&f, &se, &[1.0; 3]);
        assert_eq!(pairs.iter().filter(|p| p.is_some()).count(), 2, "{pairs:?}");
        let mut var_pairs = 0.0;
        let mut done = [false; 7];
        for k in 0..7 {
            if done[k] {
                continue;
            }
            let (i, j, _) = e[k];
            let mirror = e.iter().position(|&(a, b, _)| a == j && b == i);
            let coupled = mirror.filter(|&m| e[m].2 == e[k].2 && i != j);
            let mut t = Triplets::new((3, 3));
            for (m, &(a, b, v)) in e.iter().enumerate() {
                let bump = m == k || Some(m) == coupled;
                t.add_triplet(a, b, if bump { v + 1e-6 } else { v });
            }
            done[k] = true;
            if let Some(m) = coupled {
                done[m] = true;
            }
            let g = t.to_csr();
            let s = solve(&Problem { f: &g, ..p }, &Settings::default()).unwrap();
            let d = (s.q[0] - sol.q[0]) / 1e-6;
            var_pairs += d * d * 1e-4;
        }
        let fd = var_pairs.sqrt();
        assert!(
            (flows[0].se - fd).abs() < 1e-4 * fd,
            "adjoint {} vs differences {fd}",
            flows[0].se
        );
    }
}
