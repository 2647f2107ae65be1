//! A benchmark suite any form-factor program can be scored on: cases with exact answers,
//! a scorer, and a leaderboard.
//!
//! - [`cases`]: the catalogue. Every case is a small scene of named surfaces (planar
//!   polygons, one-sided, front counter-clockwise), a pair of them to compare (from, to),
//!   the exact surface-to-surface factor `F_AB = 1/A_A ∫_A ∫_B cos θ_x cos θ_y V / (π r²)`
//!   with its source (Howell's catalogue number, the superposition or symmetry argument),
//!   and the difficulty class it probes ([`Class`]).
//! - [`export`]: `radiosity suite export DIR` writes one OBJ/MTL per case and the table
//!   (`suite.json`, `suite.csv`) naming the suite version [`VERSION`].
//! - [`score`]: `radiosity suite score` reads a program's answers (a factors folder per
//!   case, a Matrix Market matrix with a patch table per case, or a CSV of
//!   surface-to-surface factors) and reports the error per case and per class.
//! - [`run`]: `radiosity suite run` computes this program's answers through the same path
//!   (one `factors` folder per case).
//! - [`board`]: the leaderboard: a table and an error-against-time chart of several scored
//!   programs.
//!
//! The module sits downstream of every stage (it drives the pipeline and writes files),
//! beside [`crate::study`], whose configurations it includes.

pub mod board;
pub mod cases;
pub mod export;
pub mod run;
pub mod score;

use glam::DVec3;

/// The suite's version: exported tables and score files carry it, and the scorer refuses
/// answers made for another version.
pub const VERSION: &str = "radiosity-suite/1";

/// What a case is hard for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Class {
    /// Surfaces far apart compared with their size: small factors, smooth kernel.
    Far,
    /// Surfaces close compared with their size, not touching.
    Near,
    /// Surfaces at right angles sharing (part of) an edge: the kernel is unbounded there.
    SharedEdge,
    /// Surfaces meeting at an angle other than 90°, along an edge or at a point.
    Touching,
    /// Parallel or perpendicular surfaces separated by a gap much smaller than their size.
    ThinGap,
    /// Receivers seen nearly edge-on: rays leave within a few degrees of a plane.
    Grazing,
    /// A third surface blocks part of the pair; the value follows from symmetry or
    /// superposition over the visible parts.
    Occluded,
    /// Surfaces with holes (not convex): the value is a difference of closed forms.
    Hole,
    /// A catalogue case rotated and moved away from the origin.
    RigidMotion,
    /// A catalogue case scaled to very small or very large size, or of extreme aspect.
    Scale,
    /// Closed enclosures: rows sum to 1, factors from symmetry and the catalogue.
    Enclosure,
}

impl Class {
    /// Every class, in table order.
    pub const ALL: [Class; 11] = [
        Class::Far,
        Class::Near,
        Class::SharedEdge,
        Class::Touching,
        Class::ThinGap,
        Class::Grazing,
        Class::Occluded,
        Class::Hole,
        Class::RigidMotion,
        Class::Scale,
        Class::Enclosure,
    ];

    /// The name used in files.
    pub fn name(self) -> &'static str {
        match self {
            Class::Far => "far",
            Class::Near => "near",
            Class::SharedEdge => "shared-edge",
            Class::Touching => "touching",
            Class::ThinGap => "thin-gap",
            Class::Grazing => "grazing",
            Class::Occluded => "occluded",
            Class::Hole => "hole",
            Class::RigidMotion => "rigid-motion",
            Class::Scale => "scale",
            Class::Enclosure => "enclosure",
        }
    }

    /// The class named `name` (as [`Class::name`] writes it).
    pub fn parse(name: &str) -> Option<Class> {
        Class::ALL.into_iter().find(|c| c.name() == name)
    }
}

/// A named surface of a case: planar convex polygons of 3 or 4 corners, counter-clockwise
/// seen from the front (the side that emits and receives).
#[derive(Clone, Debug, PartialEq)]
pub struct Surface {
    /// Name: the OBJ object and group, and its material.
    pub name: String,
    /// The polygons.
    pub polygons: Vec<Vec<DVec3>>,
}

impl Surface {
    /// Total area.
    pub fn area(&self) -> f64 {
        self.polygons.iter().map(|p| polygon_area(p)).sum()
    }
}

/// Area of a planar polygon (half the length of its Newell normal).
pub fn polygon_area(p: &[DVec3]) -> f64 {
    crate::scene::polygon::newell(p).length() / 2.0
}

/// One case of the suite.
#[derive(Clone, Debug)]
pub struct Case {
    /// Unique name (file stem of its OBJ).
    pub name: String,
    /// The difficulty it probes.
    pub class: Class,
    /// What it is.
    pub about: String,
    /// Surfaces of the scene, in OBJ order.
    pub surfaces: Vec<Surface>,
    /// Index of the from-surface in `surfaces`.
    pub from: usize,
    /// Index of the to-surface in `surfaces`.
    pub to: usize,
    /// Exact `F_from,to`.
    pub exact: f64,
    /// Where the exact value comes from (formula, catalogue number).
    pub source: String,
    /// The visible parts the exact value rests on: `F = Σ A_p F_pq / A_from` over these
    /// pairs of polygons `(p, q)`, each pair seeing all of each other, unblocked. Empty
    /// when nothing blocks any pair of points of the two surfaces (then the pairs are all
    /// the from-surface's polygons against all the to-surface's). The test recomputes the
    /// exact value from these by quadrature.
    pub visible: Vec<(Vec<DVec3>, Vec<DVec3>)>,
}

impl Case {
    /// The polygon pairs whose unblocked factors make up the exact value (see
    /// [`Case::visible`]).
    pub fn visible_pairs(&self) -> Vec<(Vec<DVec3>, Vec<DVec3>)> {
        if !self.visible.is_empty() {
            return self.visible.clone();
        }
        let mut out = Vec::new();
        for p in &self.surfaces[self.from].polygons {
            for q in &self.surfaces[self.to].polygons {
                out.push((p.clone(), q.clone()));
            }
        }
        out
    }

    /// 0-based indices, in OBJ `f` order, of the faces of surface `s`.
    pub fn face_indices(&self, s: usize) -> Vec<usize> {
        let start: usize = self.surfaces[..s].iter().map(|x| x.polygons.len()).sum();
        (start..start + self.surfaces[s].polygons.len()).collect()
    }
}
