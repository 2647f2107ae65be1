//! Sources near a receiver: when a source is much wider than its distance from the
//! receiver, where its visibility rays start is stratified by pieces of the source that
//! shrink towards the receiver.
//!
//! A traced visible fraction weighs each segment by the form-factor kernel
//! `cos θ_x cos θ_y / r²` ([`super::link::kernel_weight`]); its control-variate estimate
//! divides by the kernel's exact mean. Over a source `√A_s` wide at a distance `d ≪ √A_s`
//! from the receiver the kernel is concentrated on a patch about `d` across: a segment
//! landing there weighs `(√A_s / d)²` times the mean, and with the default `4 × 4`
//! segments the estimate has a heavy tail: unbiased, but now and then many times the
//! truth. On `city-16` at `--error 0.05`, wall leaves a few tenths of a metre above the
//! ground gathered ground leaves metres wide with visible fractions up to 15
//! (docs/HIERARCHY.md, *Near sources*).
//!
//! In the final gather, a leaf's rays to a near source (one not cut into its children:
//! a leaf, or one within [`NEAR_CUT`]) are drawn instead from pieces of it
//! ([`Piece::split`], the split elements use, so that a piece lies within one child of
//! the source): the piece nearest the receiver, relative to its size, is split until
//! every piece is at most [`STRATUM_CUT`] times as wide as its distance from the receiver
//! (or the receiver's own side, below which splitting the source alone does not bound the
//! kernel), and the count reaches the rays asked for. The same number of points is drawn
//! in each piece, so the pieces are the strata, and each segment's weight is its kernel
//! times its piece's Jacobian times the number of pieces: the same expectation as uniform
//! strata (the sum of the weights still averages the rays times the kernel's mean), but
//! no weight exceeds its share by more than the pieces' bounded ratio: stratified
//! sampling with strata chosen by where the integrand is large (Veach, *Robust Monte
//! Carlo methods for light transport simulation*, 1997, chapter 2).

use glam::DVec3;
use smallvec::SmallVec;

use super::element::Elements;
use crate::formfactor::exact::{polygon_distance, Piece};

/// A source more than this many times as wide (`√A`) as its distance from the receiver is
/// *near*: the final gather cuts such a source into its children when it has any
/// (`hierarchy::near_source`), and a leaf's rays to a near source are stratified by its
/// pieces ([`strata`]). On `city-2` at `--error 0.05`, wall leaves 0.2 to 0.6 m above a
/// 20 m ground gathered the whole ground with fractions far above 1 (51 leaves summed
/// their factors over 1 beyond 3 bars, the largest to 6.6); cut, none did.
pub const NEAR_CUT: f64 = 4.0;

/// A source is drawn from pieces ([`strata`]) where it is wider than its distance from the
/// receiver (floored at the receiver's side) by more than this, and split until no piece
/// is. Measured on `city-16 --error 0.05 --clusters off` (with the other two remedies of
/// *Near sources* in docs/HIERARCHY.md): leaves summing their factors over 1 beyond 3
/// bars, 108 at 4, 23 at 2, 12 at 1.5, 5 at 1, for 0.4% more rays from 4 to 1.
pub const STRATUM_CUT: f64 = 1.0;

/// Most pieces a near source is drawn from: with the receiver's side as the floor of the
/// distance, a piece `NEAR_CUT` times the receiver's side is reached after
/// `log₂(√A_s / (NEAR_CUT √A_r))` splits of three new pieces each, 24 levels of
/// difference in size before this cap.
pub const MOST_PIECES: usize = 64;

/// How the parameters of a piece map to those of the whole source.
#[derive(Clone, Copy, Debug)]
enum ToSource {
    /// A quad's parameter square `[u0, u0 + size] × [v0, v0 + size]`.
    Quad { u0: f64, v0: f64, size: f64 },
    /// A triangle's corners, as barycentric coordinates of the source's corners.
    Tri([[f64; 3]; 3]),
}

/// One piece of a near source: a stratum of its visibility rays' source points.
#[derive(Clone, Copy, Debug)]
pub struct Stratum {
    /// The piece's own parameter map.
    pub piece: Piece,
    map: ToSource,
    /// `√A` of the piece over its distance from the receiver (floored at the receiver's
    /// side), which decides the piece split next, when `exact`; until then an upper bound
    /// on it, from the two polygons' enclosing balls ([`Stratum::settle`]).
    nearness: f64,
    exact: bool,
}

/// The receiver as [`strata`] measures the pieces' distances from it: its corners, an
/// enclosing ball, and the floor of the distance (its side).
struct Receiver<'a> {
    corners: &'a [DVec3],
    centre: DVec3,
    radius: f64,
    floor: f64,
}

impl Receiver<'_> {
    /// A lower bound on the distance of `piece` from the receiver: their enclosing balls'
    /// gap ([`Piece::ball`]), less a relative `1e-12` so that rounding cannot put it above
    /// the polygons' distance.
    fn below(&self, piece: &Piece) -> f64 {
        let (c, r) = piece.ball();
        let d = c.distance(self.centre);
        d - r - self.radius - 1e-12 * (d + r + self.radius)
    }
}

impl Stratum {
    /// The source's parameters of the piece's point at `(u, v)`.
    pub fn to_source(&self, u: f64, v: f64) -> (f64, f64) {
        match self.map {
            ToSource::Quad { u0, v0, size } => (u0 + size * u, v0 + size * v),
            ToSource::Tri(b) => {
                // The collapsed map's barycentrics `(1 - u, u (1 - v), u v)`, then the
                // source's `u = 1 - λ₀`, `v = λ₂ / u`.
                let l = [1.0 - u, u * (1.0 - v), u * v];
                let lam: [f64; 3] =
                    std::array::from_fn(|j| (0..3).map(|i| l[i] * b[i][j]).sum::<f64>());
                let us = (1.0 - lam[0]).clamp(0.0, 1.0);
                let vs = if us > 0.0 {
                    (lam[2] / us).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                (us, vs)
            }
        }
    }

    /// The four pieces of [`Piece::split`], in its order, with their maps.
    fn split(&self, receiver: &Receiver) -> [Stratum; 4] {
        let pieces = self.piece.split();
        std::array::from_fn(|k| {
            let map = match self.map {
                ToSource::Quad { u0, v0, size } => {
                    let h = 0.5 * size;
                    let (du, dv) = [(0.0, 0.0), (h, 0.0), (h, h), (0.0, h)][k];
                    ToSource::Quad {
                        u0: u0 + du,
                        v0: v0 + dv,
                        size: h,
                    }
                }
                ToSource::Tri(b) => {
                    let mid = |i: usize, j: usize| -> [f64; 3] {
                        std::array::from_fn(|c| 0.5 * (b[i][c] + b[j][c]))
                    };
                    let (m01, m12, m20) = (mid(0, 1), mid(1, 2), mid(2, 0));
                    ToSource::Tri(match k {
                        0 => [b[0], m01, m20],
                        1 => [m01, b[1], m12],
                        2 => [m20, m12, b[2]],
                        _ => [m12, m20, m01],
                    })
                }
            };
            Stratum::new(pieces[k], map, receiver)
        })
    }

    /// The piece with the upper bound on its nearness.
    fn new(piece: Piece, map: ToSource, receiver: &Receiver) -> Stratum {
        let below = receiver.below(&piece).max(receiver.floor);
        Stratum {
            piece,
            map,
            nearness: piece.area().sqrt() / below,
            exact: false,
        }
    }

    /// The piece's nearness made exact: `√A` over the polygons' distance (floored).
    fn settle(&mut self, receiver: &Receiver) {
        if !self.exact {
            let d = polygon_distance(self.piece.corners(), receiver.corners).max(receiver.floor);
            self.nearness = self.piece.area().sqrt() / d;
            self.exact = true;
        }
    }
}

/// True when `s` is more than `cut` times as wide (`√A_s`) as its distance from `r`, that
/// distance floored at `floor`: a bound from the two elements' enclosing balls first, the
/// polygons' distance only where that bound does not settle it.
pub fn is_near(e: &Elements, r: u32, s: u32, floor: f64, cut: f64) -> bool {
    let side = e.area[s as usize].sqrt();
    side > cut * floor
        && side > cut * apart(e, r, s)
        && side > cut * polygon_distance(e.corners(r), e.corners(s))
}

/// A lower bound on the distance between elements `r` and `s`: their centres' distance
/// less each one's reach from its centre (negative where the balls overlap).
fn apart(e: &Elements, r: u32, s: u32) -> f64 {
    let (ri, si) = (r as usize, s as usize);
    let reach = |c: DVec3, p: &[DVec3]| p.iter().map(|&q| q.distance(c)).fold(0.0, f64::max);
    let (cr, cs) = (e.centre[ri], e.centre[si]);
    cr.distance(cs) - reach(cr, e.corners(r)) - reach(cs, e.corners(s))
}

/// True when elements `r` and `s` touch (their polygons within `tol`): along the contact
/// the form-factor kernel is unbounded.
pub fn touching(e: &Elements, r: u32, s: u32, tol: f64) -> bool {
    apart(e, r, s) <= tol && polygon_distance(e.corners(r), e.corners(s)) <= tol
}

/// The strata of the rays from `r` to `s` when `s` is near `r` by [`STRATUM_CUT`]
/// ([`is_near`], the distance floored at `r`'s side), at least `rays` of them; `None`
/// otherwise, and then the rays are drawn from `s`'s parameter square as a whole.
pub fn strata(e: &Elements, r: u32, s: u32, rays: usize) -> Option<SmallVec<[Stratum; 16]>> {
    let floor = e.area[r as usize].sqrt();
    if !is_near(e, r, s, floor, STRATUM_CUT) {
        return None;
    }
    let si = s as usize;
    let pr = e.corners(r);
    let whole = match e.piece[si] {
        Piece::Quad(_) => ToSource::Quad {
            u0: 0.0,
            v0: 0.0,
            size: 1.0,
        },
        Piece::Tri(_) => ToSource::Tri([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
    };
    let (centre, radius) = e.piece[r as usize].ball();
    let receiver = Receiver {
        corners: pr,
        centre,
        radius,
        floor,
    };
    let root = Stratum::new(e.piece[si], whole, &receiver);
    let mut out: SmallVec<[Stratum; 16]> = smallvec::smallvec![root];
    while out.len() + 3 <= MOST_PIECES {
        // The nearest piece for its size (the first of equals: the same on every run),
        // by the pieces' bounds, each made exact only when it comes first: the first
        // of the largest bounds, once exact, is the first of the largest nearnesses (every
        // piece before it is bounded below it, every other at most by it). A polygons'
        // distance is the costly part; most pieces never need theirs.
        let (k, near) = out
            .iter()
            .enumerate()
            .fold((0, f64::NEG_INFINITY), |best, (k, p)| {
                if p.nearness > best.1 {
                    (k, p.nearness)
                } else {
                    best
                }
            });
        if near <= STRATUM_CUT && out.len() >= rays {
            break;
        }
        if !out[k].exact {
            out[k].settle(&receiver);
            continue;
        }
        let parts = out[k].split(&receiver);
        out[k] = parts[0];
        out.extend_from_slice(&parts[1..]);
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 0.5 m wall facing -y from height `z` up, near the sources' first corner.
    fn wall(z: f64) -> Piece {
        Piece::Quad([
            DVec3::new(1.0, 1.0, z),
            DVec3::new(1.5, 1.0, z),
            DVec3::new(1.5, 1.0, z + 0.5),
            DVec3::new(1.0, 1.0, z + 0.5),
        ])
    }

    /// Each piece's points are the source's points at the parameters [`Stratum::to_source`]
    /// gives, for quads and triangles three levels down; the pieces' areas add up to the
    /// source's; and every piece ends within the near bound or the floor.
    #[test]
    fn pieces_map_back_to_their_source_and_cover_it() {
        for piece in [
            Piece::Quad([
                DVec3::new(0.0, 0.0, 0.0),
                DVec3::new(20.0, 0.0, 0.0),
                DVec3::new(21.0, 18.0, 0.0),
                DVec3::new(-1.0, 20.0, 0.0),
            ]),
            Piece::Tri([
                DVec3::new(0.0, 0.0, 0.0),
                DVec3::new(20.0, 0.0, 0.0),
                DVec3::new(3.0, 17.0, 0.0),
            ]),
        ] {
            let mut e = Elements::default();
            let s = e.add_root(piece, DVec3::Z);
            // A small wall standing 0.2 m above the source, near its first corner.
            let r = e.add_root(wall(0.2), DVec3::new(0.0, -1.0, 0.0));
            let got = strata(&e, r, s, 16).expect("a 20 m source 0.2 m away is near");
            assert!(got.len() >= 16 && got.len() <= MOST_PIECES, "{}", got.len());
            let area: f64 = got.iter().map(|p| p.piece.area()).sum();
            assert!((area / e.area[s as usize] - 1.0).abs() < 1e-12, "{area}");
            let floor = e.area[r as usize].sqrt();
            for p in &got {
                let d = polygon_distance(p.piece.corners(), e.corners(r)).max(floor);
                let nearness = p.piece.area().sqrt() / d;
                assert!(
                    nearness <= p.nearness * (1.0 + 1e-12),
                    "{nearness} over its bound"
                );
                assert!(nearness <= NEAR_CUT, "{nearness}");
                for (u, v) in [(0.1, 0.2), (0.9, 0.5), (0.5, 0.99), (0.0, 0.0)] {
                    let (us, vs) = p.to_source(u, v);
                    let a = p.piece.at(u, 1.0 - u, v, 1.0 - v).0;
                    let b = e.point(s, us, vs).0;
                    assert!(a.distance(b) < 1e-9, "{a} vs {b}");
                }
            }
            // Far from the source, or as wide as it: drawn as a whole.
            let far = e.add_root(wall(30.0), DVec3::new(0.0, -1.0, 0.0));
            assert!(strata(&e, far, s, 16).is_none());
            assert!(strata(&e, s, r, 16).is_none());
        }
    }
}
