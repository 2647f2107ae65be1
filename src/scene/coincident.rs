//! Faces that lie on other faces and face the same way: a rug modelled on the floor, a
//! decal on a wall, a duplicated face, or, in a two-sided scene, the inside of a box's
//! bottom on the floor it stands on (the box's bottom and the floor are both sheets seen
//! from both sides there). Two such faces occupy the same points, and every ray test sees
//! both: a ray to a point of one passes the other at its very end, inside the offset every
//! ray end keeps off its surface (`visibility` module docs). So whatever sees the place
//! receives the light of both and sends light to both: the light arriving there is
//! counted twice (a row of form factors sums to more than 1), and light reaches, through
//! the contact, places nothing could see (the inside of a closed box through its bottom).
//!
//! [`Scene::raise_coincident`] finds such pairs and raises one face of each off the
//! other, along its normal, by [`RAISE_REL`] of the scene diagonal: then the raised face
//! covers the other one where they overlap, as a thing lying on a surface covers it. The
//! raised face is the one of the smaller object (a rug is on the floor, not the floor on
//! the rug); within one object, the smaller face, and of two equal ones the later in the
//! file. Only that side moves: the other side of a two-sided face stays where it was (a
//! box's bottom, two-sided, on a two-sided floor: its inside rises off the floor's top, so
//! that the box is closed and the floor under it hidden; the floor stays). Faces in a
//! plane with the whole scene behind it are left alone, as nothing sees them (the box's
//! outside on the floor's underside, when nothing is under the floor). Faces raised onto
//! yet another face are raised again, up to [`MAX_ROUNDS`] times.
//!
//! Two faces *coincide* when they face the same way (normals within `1e-6` in cosine),
//! every corner of each is within [`TOUCH_REL`] of the scene diagonal of the other's
//! plane, and their overlap, the convex polygon one clips out of the other
//! (Sutherland and Hodgman 1974, "Reentrant polygon clipping", *CACM* 17), has at least
//! `1e-6` of the smaller face's area (neighbours that share an edge overlap in a segment,
//! area 0). Candidate pairs come from a sweep over the faces' bounds sorted along the
//! scene's longest axis, so a scene of `n` faces costs `O(n log n)` plus its overlapping
//! bounds.

use glam::{DVec2, DVec3};

use super::{polygon, Face, Scene};

/// Distance a face is raised off the face it lies on, as a fraction of the scene diagonal.
/// A segment ray stops `1e-4` of its length short of its far end, itself offset off its
/// surface by `1e-5` of the diagonal (`visibility::SEGMENT_TFAR`, `visibility::OFFSET_REL`),
/// so it stops at most `1.1e-4` of the diagonal above the surface it aims at; a face raised
/// by more than that blocks every ray to the surface under it.
pub const RAISE_REL: f64 = 2e-4;

/// Planes nearer than this fraction of the scene diagonal are one plane for
/// [`Scene::raise_coincident`]: the ray offset, under which ray tests cannot tell them
/// apart.
pub const TOUCH_REL: f64 = 1e-5;

/// Rounds of [`Scene::raise_coincident`]: a face raised onto another raised face (a decal
/// on a rug on a floor) is raised again, this many times at most.
pub const MAX_ROUNDS: usize = 8;

/// Least cosine between the normals of faces that face the same way.
const SAME_WAY: f64 = 1.0 - 1e-6;

/// Least overlap, as a fraction of the smaller face's area, that makes faces coincide.
const MIN_OVERLAP: f64 = 1e-6;

/// One face raised off another by [`Scene::raise_coincident`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Raised {
    /// The face raised (its other side, for a two-sided face, went with it).
    pub face: u32,
    /// A face it lay on, facing the same way.
    pub on: u32,
    /// The area where they overlapped, in square scene units.
    pub overlap: f64,
}

/// What the sweep needs of one face.
struct Plane {
    normal: DVec3,
    offset: f64,
    area: f64,
    lo: DVec3,
    hi: DVec3,
}

impl Plane {
    fn of(scene: &Scene, f: &Face) -> Plane {
        let p: Vec<DVec3> = f
            .corner_slice()
            .iter()
            .map(|&c| scene.positions[c as usize])
            .collect();
        let newell = polygon::newell(&p);
        let normal = newell.normalize_or_zero();
        let (mut lo, mut hi) = (p[0], p[0]);
        for q in &p {
            lo = lo.min(*q);
            hi = hi.max(*q);
        }
        Plane {
            normal,
            offset: normal.dot(p[0]),
            area: 0.5 * newell.length(),
            lo,
            hi,
        }
    }
}

/// Twice the signed area of a polygon in 2D (counter-clockwise positive).
fn area2(q: &[DVec2]) -> f64 {
    (0..q.len())
        .map(|k| q[k].perp_dot(q[(k + 1) % q.len()]))
        .sum()
}

/// The part of convex polygon `subject` inside convex polygon `clip`, both
/// counter-clockwise (Sutherland and Hodgman 1974).
fn clip_convex(subject: &[DVec2], clip: &[DVec2]) -> Vec<DVec2> {
    let mut out = subject.to_vec();
    for k in 0..clip.len() {
        let (a, b) = (clip[k], clip[(k + 1) % clip.len()]);
        let side = |p: DVec2| (b - a).perp_dot(p - a);
        let input = std::mem::take(&mut out);
        for i in 0..input.len() {
            let (p, q) = (input[i], input[(i + 1) % input.len()]);
            let (sp, sq) = (side(p), side(q));
            if sp >= 0.0 {
                out.push(p);
            }
            if (sp >= 0.0) != (sq >= 0.0) {
                out.push(p + (q - p) * (sp / (sp - sq)));
            }
        }
        if out.is_empty() {
            break;
        }
    }
    out
}

impl Scene {
    /// The area where faces `a` and `b` overlap when they coincide (module docs), with
    /// planes `pa`, `pb` and `touch` the largest distance of a corner from the other's
    /// plane; `None` when they do not.
    fn coincidence(&self, a: usize, b: usize, pa: &Plane, pb: &Plane, touch: f64) -> Option<f64> {
        if pa.normal.dot(pb.normal) < SAME_WAY {
            return None;
        }
        let corners = |f: usize| {
            self.faces[f]
                .corner_slice()
                .iter()
                .map(|&c| self.positions[c as usize])
                .collect::<Vec<_>>()
        };
        let (ca, cb) = (corners(a), corners(b));
        let near = |c: &[DVec3], p: &Plane| {
            c.iter()
                .all(|q| (p.normal.dot(*q) - p.offset).abs() <= touch)
        };
        if !near(&ca, pb) || !near(&cb, pa) {
            return None;
        }
        // Both in the 2D frame of `a`'s plane, where both wind counter-clockwise.
        let u = pa.normal.any_orthonormal_vector();
        let v = pa.normal.cross(u);
        let flat = |c: &[DVec3]| -> Vec<DVec2> {
            c.iter()
                .map(|q| DVec2::new(u.dot(*q - ca[0]), v.dot(*q - ca[0])))
                .collect()
        };
        let overlap = 0.5 * area2(&clip_convex(&flat(&cb), &flat(&ca)));
        (overlap >= MIN_OVERLAP * pa.area.min(pb.area)).then_some(overlap)
    }

    /// True when some corner of the scene lies in front of `plane` by more than `touch`:
    /// only then can anything see the faces lying in it (the outside of a room's floor
    /// has the whole scene behind it, and raising a face off it would only take the floor
    /// off the scene's hull, where the semi-analytic estimator proves it blocks nothing).
    /// The scene's bounds `lo`, `hi` decide most planes at once.
    fn seen(&self, plane: &Plane, touch: f64, (lo, hi): (DVec3, DVec3)) -> bool {
        let n = plane.normal;
        let upper = (n * lo).max(n * hi).element_sum() - plane.offset;
        upper > touch
            && self.faces.iter().any(|f| {
                f.corner_slice()
                    .iter()
                    .any(|&c| n.dot(self.positions[c as usize]) - plane.offset > touch)
            })
    }

    /// Raises faces that lie on other faces facing the same way (module docs), records a
    /// warning in [`Scene::warnings`] when it raised any, and returns what it raised. A
    /// scene without such faces is left exactly as it was.
    pub fn raise_coincident(&mut self) -> Vec<Raised> {
        let (lo, hi) = self.bounds();
        let diagonal = (hi - lo).length();
        if !diagonal.is_finite() || diagonal <= 0.0 {
            return Vec::new();
        }
        let touch = TOUCH_REL * diagonal;
        let lift = RAISE_REL * diagonal;
        let mut raised: Vec<Raised> = Vec::new();
        for _ in 0..MAX_ROUNDS {
            let found = self.raise_round(touch, lift);
            if found.is_empty() {
                break;
            }
            raised.extend(found);
        }
        if let Some(first) = raised.first() {
            let at = |f: u32| {
                let face = &self.faces[f as usize];
                let object = &self.objects[face.object as usize];
                let side = if face.back { " (its back)" } else { "" };
                match face.line {
                    0 => format!("a face of `{object}`{side}"),
                    l => format!("the face of `{object}` at line {l}{side}"),
                }
            };
            let mut faces: Vec<u32> = raised.iter().map(|r| r.face).collect();
            faces.sort_unstable();
            faces.dedup();
            self.warnings.push(format!(
                "{}: {} face(s) lay on other faces facing the same way, where both would \
                 receive the same light, counted twice (first: {} on {}, overlapping {:.3e} \
                 square units); each was raised off the face under it by {:.3e} ({RAISE_REL} \
                 of the scene diagonal), so that it covers it: the face of the smaller \
                 object lies on top. Remove or move hidden faces to silence this",
                self.source,
                faces.len(),
                at(first.face),
                at(first.on),
                first.overlap,
                lift
            ));
        }
        raised
    }

    /// One round of [`Scene::raise_coincident`]: finds the coinciding pairs, and raises
    /// the upper face of each.
    fn raise_round(&mut self, touch: f64, lift: f64) -> Vec<Raised> {
        let planes: Vec<Plane> = self.faces.iter().map(|f| Plane::of(self, f)).collect();
        let (lo, hi) = self.bounds();
        let e = hi - lo;
        let axis = if e.x >= e.y && e.x >= e.z {
            0
        } else if e.y >= e.z {
            1
        } else {
            2
        };
        let mut order: Vec<usize> = (0..self.faces.len()).collect();
        order.sort_by(|&a, &b| planes[a].lo[axis].total_cmp(&planes[b].lo[axis]));
        // The area of each object, front sides only: the smaller object lies on top.
        let mut object_area = vec![0.0; self.objects.len()];
        for (f, p) in self.faces.iter().zip(&planes) {
            if !f.back {
                object_area[f.object as usize] += p.area;
            }
        }
        // Upper face of each pair, the face under it and the overlap.
        let mut pairs: Vec<(usize, usize, f64)> = Vec::new();
        let mut seen_from: Vec<Option<bool>> = vec![None; self.faces.len()];
        for (k, &a) in order.iter().enumerate() {
            for &b in &order[k + 1..] {
                if planes[b].lo[axis] > planes[a].hi[axis] + touch {
                    break;
                }
                let apart = (planes[a].lo - touch).cmpgt(planes[b].hi).any()
                    || (planes[b].lo - touch).cmpgt(planes[a].hi).any();
                if apart {
                    continue;
                }
                let Some(overlap) = self.coincidence(a, b, &planes[a], &planes[b], touch) else {
                    continue;
                };
                // Once per face: a face may lie on many (a stack, a tessellated floor).
                let seen =
                    *seen_from[a].get_or_insert_with(|| self.seen(&planes[a], touch, (lo, hi)));
                if !seen {
                    continue;
                }
                let (fa, fb) = (&self.faces[a], &self.faces[b]);
                let size = |f: usize| {
                    let face = &self.faces[f];
                    if fa.object != fb.object {
                        object_area[face.object as usize]
                    } else {
                        planes[f].area
                    }
                };
                // Smaller on top; of equal sizes the later face (by index).
                let a_on_top = match size(a).total_cmp(&size(b)) {
                    std::cmp::Ordering::Less => true,
                    std::cmp::Ordering::Greater => false,
                    std::cmp::Ordering::Equal => a > b,
                };
                let (top, under) = if a_on_top { (a, b) } else { (b, a) };
                pairs.push((top, under, overlap));
            }
        }
        // Each face is raised once, along its own normal, on corners of its own (its
        // other side, for a two-sided face, stays where it was).
        pairs.sort_by_key(|&(top, under, _)| (top, under));
        let mut done = vec![false; self.faces.len()];
        let mut raised = Vec::new();
        for (top, under, overlap) in pairs {
            if done[top] {
                continue;
            }
            done[top] = true;
            let shift = planes[top].normal * lift;
            for k in 0..self.faces[top].len() {
                let c = self.faces[top].corners[k] as usize;
                self.positions.push(self.positions[c] + shift);
                self.faces[top].corners[k] = (self.positions.len() - 1) as u32;
            }
            raised.push(Raised {
                face: top as u32,
                on: under as u32,
                overlap,
            });
        }
        raised
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;

    fn parse(obj: &str) -> Scene {
        super::super::obj::parse("t", Path::new("t.obj"), obj, &|_| unreachable!()).unwrap()
    }

    /// Corners of face `f`.
    fn corners(s: &Scene, f: usize) -> Vec<DVec3> {
        s.faces[f]
            .corner_slice()
            .iter()
            .map(|&c| s.positions[c as usize])
            .collect()
    }

    #[test]
    fn clipping_gives_the_overlap_of_two_squares() {
        let sq = |x: f64, y: f64| {
            vec![
                DVec2::new(x, y),
                DVec2::new(x + 1.0, y),
                DVec2::new(x + 1.0, y + 1.0),
                DVec2::new(x, y + 1.0),
            ]
        };
        let a = 0.5 * area2(&clip_convex(&sq(0.25, 0.5), &sq(0.0, 0.0)));
        assert!((a - 0.375).abs() < 1e-15, "{a}");
        // Sharing an edge only: no area.
        assert!(area2(&clip_convex(&sq(1.0, 0.0), &sq(0.0, 0.0))).abs() < 1e-15);
        assert!(clip_convex(&sq(3.0, 0.0), &sq(0.0, 0.0)).is_empty());
    }

    #[test]
    fn a_rug_on_the_floor_is_raised_and_the_floor_is_not() {
        // A 4 x 4 floor at y = 0 and a 1 x 1 rug on it, both facing up, in different
        // objects; a wall facing +x shares the floor's edge.
        let mut s = parse(
            "o floor\nv 0 0 0\nv 0 0 4\nv 4 0 4\nv 4 0 0\nf 1 2 3 4\n\
             o rug\nv 1 0 1\nv 1 0 2\nv 2 0 2\nv 2 0 1\nf 5 6 7 8\n\
             o wall\nv 0 0 0\nv 0 3 0\nv 0 3 4\nv 0 0 4\nf 9 10 11 12\n",
        );
        let floor = corners(&s, 0);
        let wall = corners(&s, 2);
        let raised = s.raise_coincident();
        assert_eq!(raised.len(), 1, "{raised:?}");
        assert_eq!((raised[0].face, raised[0].on), (1, 0));
        assert!((raised[0].overlap - 1.0).abs() < 1e-12);
        // The diagonal of the 4 x 3 x 4 bounds is sqrt(41).
        let lift = RAISE_REL * 41f64.sqrt();
        for q in corners(&s, 1) {
            assert!((q.y - lift).abs() < 1e-15, "{q}");
        }
        assert_eq!(corners(&s, 0), floor);
        assert_eq!(corners(&s, 2), wall);
        let told = |s: &Scene| -> Vec<String> {
            s.warnings
                .iter()
                .filter(|w| w.contains("facing the same way"))
                .cloned()
                .collect()
        };
        assert_eq!(told(&s).len(), 1);
        assert!(told(&s)[0].contains("`rug` at line 12 on the face of `floor` at line 6"));
        // Done once: nothing left to raise.
        assert!(s.raise_coincident().is_empty());
        assert_eq!(told(&s).len(), 1);
    }

    #[test]
    fn faces_that_only_touch_or_face_apart_are_left_alone() {
        let obj = "v 0 0 0\nv 0 0 1\nv 1 0 1\nv 1 0 0\nv 2 0 1\nv 2 0 0\n\
                   f 1 2 3 4\nf 4 3 5 6\nf 4 3 2 1\n";
        // Neighbours sharing an edge, and a face back to back with the first (one-sided:
        // a box's bottom on a floor).
        let mut s = parse(obj);
        let before = s.clone();
        assert!(s.raise_coincident().is_empty());
        assert_eq!(s.positions, before.positions);
        assert_eq!(s.faces, before.faces);
        assert_eq!(s.warnings, before.warnings);
    }

    #[test]
    fn a_two_sided_box_bottom_covers_the_floor_from_inside_the_box() {
        // A floor facing up, and a closed unit box on it whose bottom faces down, both
        // made two-sided: the bottom's inside then lies on the floor's front.
        let mut s = parse(
            "o floor\nv -2 0 -2\nv -2 0 2\nv 2 0 2\nv 2 0 -2\nf 1 2 3 4\n\
             o box\nv 0 0 0\nv 1 0 0\nv 1 0 1\nv 0 0 1\nv 0 1 0\nv 1 1 0\nv 1 1 1\nv 0 1 1\n\
             f 5 6 7 8\nf 9 12 11 10\nf 5 9 10 6\nf 6 10 11 7\nf 7 11 12 8\nf 8 12 9 5\n",
        );
        assert_eq!(s.make_two_sided(true), 7);
        let (lo, hi) = s.bounds();
        let lift = RAISE_REL * (hi - lo).length();
        let raised = s.raise_coincident();
        // The bottom's inside (face 8, the back of face 1, facing up) is raised off the
        // floor's top (face 0); its outside (face 1, facing down) lies on the floor's
        // underside (face 7, the floor's back), which nothing sees: left alone.
        let bottom = 1;
        let inside = s.faces[bottom].twin as usize;
        let pairs: Vec<(u32, u32)> = raised.iter().map(|r| (r.face, r.on)).collect();
        assert_eq!(pairs, [(inside as u32, 0)]);
        for (f, y) in [(bottom, 0.0), (inside, lift)] {
            for q in corners(&s, f) {
                assert!((q.y - y).abs() < 1e-15, "face {f}: {q}");
            }
        }
        // The floor and the walls keep their corners at y = 0.
        assert!(corners(&s, 0).iter().all(|q| q.y == 0.0));
        assert!(corners(&s, 3).iter().any(|q| q.y == 0.0));
        assert!(s.raise_coincident().is_empty());
    }

    #[test]
    fn a_duplicated_face_is_raised_once_and_a_stack_rises_in_steps() {
        // The same square three times in one object, under a lid facing it: the second is
        // raised off the first, then the third off the raised second. Without the lid
        // nothing sees them, and nothing is raised.
        let squares = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\nf 1 2 3 4\nf 1 2 3 4\n";
        assert!(parse(squares).raise_coincident().is_empty());
        let mut s = parse(&format!("{squares}v 0 0 1\nv 0 1 1\nv 1 0 1\nf 5 6 7\n"));
        let raised = s.raise_coincident();
        let (lo, hi) = s.bounds();
        let z: Vec<f64> = (0..3).map(|f| corners(&s, f)[0].z).collect();
        assert_eq!(raised.len(), 3, "{raised:?}");
        assert_eq!(z[0], 0.0);
        let mut zs = z.clone();
        zs.sort_by(f64::total_cmp);
        assert!(zs[1] > 0.0 && zs[2] > zs[1], "{z:?}");
        assert!((hi - lo).length() > 0.0);
    }
}
