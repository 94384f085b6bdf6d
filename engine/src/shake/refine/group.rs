//! Which particles one camera's shake fits together, and what each fit says of them: every
//! predicted particle's group (its own image and the tracked ones that may touch it), groups
//! that share a particle fitted as one, and each particle judged on its own group's pixels.

use super::{
    boxes, fit, rms_within, stayed, window, Fitted, Free, Measured, Member, Neighbourhood, Seen,
    Shape, Wanted, MARGIN_PX,
};
use crate::geometry::{PixelPoint, RectPoint};
use crate::spatial::{PointGrid, GRID_CELL_PX};
use crate::ImageView;

/// One camera's particles as fit members: per detection, the track's member that claimed it
/// (with whether the detection is clear); per wanted particle without a detection, its member
/// at its prediction.
pub(super) struct Members {
    claimed: Vec<Option<(Member, bool)>>,
    hidden: Vec<Option<Member>>,
}

/// Every wanted particle's member, where its track knows its shape (`shapes`, or
/// `other_camera`'s): claimed detections seeded at their centroid if clear, else at the
/// prediction; particles without a detection at their prediction.
pub(super) fn members_of(
    seen: &[Seen],
    wanted: &[Wanted],
    shapes: &[Option<Shape>],
    other_camera: &[Option<Shape>],
) -> Members {
    let mut members = Members {
        claimed: vec![None; seen.len()],
        hidden: vec![None; wanted.len()],
    };
    for (k, w) in wanted.iter().enumerate() {
        let Some(shape) = best_known(shapes[k], other_camera[k]) else {
            continue;
        };
        match w.detection {
            Some(i) => {
                let clear = seen[i].clear;
                let at = match w.predicted_px {
                    Some(p) if !clear => p,
                    _ => seen[i].centroid,
                };
                members.claimed[i] = Some((Member { at, shape }, clear));
            }
            None => members.hidden[k] = w.predicted_px.map(|at| Member { at, shape }),
        }
    }
    members
}

/// One camera's particles, as a wanted particle's group fit sees them.
pub(super) struct Group<'a> {
    image: ImageView<'a>,
    seen: &'a [Seen],
    wanted: &'a [Wanted],
    members: &'a Members,
    near: &'a Neighbourhood,
    /// The particles without a detection, by where their tracks put them.
    hidden_grid: PointGrid,
    edge_px: f64,
    widest_px: f64,
    max_rms: f64,
}

/// Wanted particle `k`'s fit: its group (`members`, its own first, then the tracked
/// particles whose images may touch it; `ids` name them across groups), where in the group
/// the particles without a detection are, and the detections no track knows that may touch it.
struct Subject {
    k: usize,
    members: Vec<Member>,
    ids: Vec<usize>,
    hidden: Vec<usize>,
    unknown: Vec<Member>,
}

impl<'a> Group<'a> {
    /// One camera's wanted particles (`seen` its detections) with their `members`; `edge_px`
    /// and `widest_px` shape the detections no track knows, `max_rms` is the lone bound.
    pub(super) fn new(
        (image, seen, wanted): (ImageView<'a>, &'a [Seen], &'a [Wanted]),
        members: &'a Members,
        near: &'a Neighbourhood,
        (edge_px, widest_px, max_rms): (f64, f64, f64),
    ) -> Self {
        let hidden_grid = PointGrid::new(
            wanted
                .iter()
                .enumerate()
                .filter(|(k, _)| members.hidden[*k].is_some())
                .map(|(k, w)| (w.predicted_rect, k)),
            GRID_CELL_PX,
        );
        Self {
            image,
            seen,
            wanted,
            members,
            near,
            hidden_grid,
            edge_px,
            widest_px,
            max_rms,
        }
    }

    /// Every wanted particle measured among its neighbours (`None`: not fitted). Groups that
    /// share a particle are fitted as one, once; a particle whose verdict that fit does not
    /// give is fitted again with its own group alone (unless its group is the whole of the
    /// joint fit, which was then its own group's fit and judged as such), then with the
    /// detections no track knows.
    pub(super) fn measure_all(&self) -> Vec<Option<Measured>> {
        let subjects: Vec<Option<Subject>> =
            (0..self.wanted.len()).map(|k| self.subject(k)).collect();
        let mut measured = vec![None; subjects.len()];
        let mut fitted_alone = vec![false; subjects.len()];
        for cluster in self.clusters(&subjects) {
            let group: Vec<&Subject> = cluster
                .iter()
                .filter_map(|&k| subjects[k].as_ref())
                .collect();
            if group.len() > 1 {
                for (k, m, alone) in self.measure_together(&group) {
                    measured[k] = m;
                    fitted_alone[k] = alone;
                }
            }
            for s in group {
                if measured[s.k].is_none() {
                    measured[s.k] = self.measure(s, fitted_alone[s.k]);
                }
            }
        }
        measured
    }

    /// The wanted particles with a fit, in groups that share a particle.
    fn clusters(&self, subjects: &[Option<Subject>]) -> Vec<Vec<usize>> {
        let mut parent: Vec<usize> = (0..subjects.len()).collect();
        fn root(parent: &mut [usize], mut i: usize) -> usize {
            while parent[i] != i {
                parent[i] = parent[parent[i]];
                i = parent[i];
            }
            i
        }
        let mut holder = vec![usize::MAX; self.seen.len() + self.wanted.len()];
        for s in subjects.iter().flatten() {
            for &id in &s.ids {
                if holder[id] == usize::MAX {
                    holder[id] = s.k;
                } else {
                    let (a, b) = (root(&mut parent, holder[id]), root(&mut parent, s.k));
                    parent[a] = b;
                }
            }
        }
        let mut clusters: Vec<Vec<usize>> = vec![Vec::new(); subjects.len()];
        for s in subjects.iter().flatten() {
            let r = root(&mut parent, s.k);
            clusters[r].push(s.k);
        }
        clusters.retain(|c| !c.is_empty());
        clusters
    }

    /// Groups that share particles fitted as one; each one's verdict judged on its own
    /// members and its own pixels, and whether its group is the whole of the joint fit (which
    /// was then its own group's fit, judged also as that fit would be: a particle without a
    /// detection on its own pixels alone).
    fn measure_together(&self, group: &[&Subject]) -> Vec<(usize, Option<Measured>, bool)> {
        let mut slot = std::collections::HashMap::new();
        let mut seeds = Vec::new();
        for s in group {
            for (&id, m) in s.ids.iter().zip(&s.members) {
                slot.entry(id).or_insert_with(|| {
                    seeds.push(*m);
                    seeds.len() - 1
                });
            }
        }
        let samples = window(self.image, &boxes(&seeds));
        let Some(fitted) = fit(&samples, &seeds, Free::GuessedRadius) else {
            return Vec::new();
        };
        let residuals = fitted.residuals(&samples);
        let judged_on = |s: &Subject, own: &[Member]| {
            let fitted = Fitted {
                members: s.ids.iter().map(|id| fitted.members[slot[id]]).collect(),
                rms: rms_within(&samples, &residuals, &boxes(own)),
                floor: fitted.floor,
                settled: fitted.settled,
            };
            self.judge(s, &s.members, fitted)
        };
        group
            .iter()
            .map(|s| {
                let alone = s.ids.len() == seeds.len();
                let mut measured = judged_on(s, &s.members);
                if measured.is_none() && alone && self.wanted[s.k].detection.is_none() {
                    measured = judged_on(s, &s.members[..1]);
                }
                (s.k, measured, alone)
            })
            .collect()
    }

    /// Wanted particle `k`'s fit, `None` where it is not fitted (no shape known, or a clear
    /// detection with no hidden particle near).
    fn subject(&self, k: usize) -> Option<Subject> {
        let w = &self.wanted[k];
        let (own, clear, c, id) = match w.detection {
            Some(i) => {
                let (own, clear) = self.members.claimed[i]?;
                (own, clear, self.seen[i].rect, i)
            }
            None => {
                let own = self.members.hidden[k]?;
                if !within(self.image, own.at, own.shape.reach_px()) {
                    return None;
                }
                (own, false, w.predicted_rect, self.seen.len() + k)
            }
        };
        let (members, ids, unknown, hidden) = self.neighbours(k, (own, id), c);
        if clear && hidden.is_empty() {
            return None;
        }
        Some(Subject {
            k,
            members,
            ids,
            hidden,
            unknown,
        })
    }

    /// Wanted particle `k` measured in a fit of its own group: the tracked particles' models
    /// first (unless that fit was already made, `fitted_alone`); detections no track knows
    /// join only where those do not explain the pixels (most are fragments of a tracked
    /// particle's image).
    fn measure(&self, s: &Subject, fitted_alone: bool) -> Option<Measured> {
        let measured = if fitted_alone {
            None
        } else {
            self.refit(s, &s.members)
                .and_then(|f| self.judge(s, &s.members, f))
        };
        if measured.is_some() || s.unknown.is_empty() {
            return measured;
        }
        let mut members = s.members.clone();
        members.extend(&s.unknown);
        self.refit(s, &members)
            .and_then(|f| self.judge(s, &members, f))
    }

    /// A group (`members`, the subject's own first) fitted, with the RMS residual its verdict
    /// rests on. A particle without a detection is judged on its own pixels: whether it is
    /// there is what they tell, while its neighbours' pixels may hold light no track knows
    /// (their own neighbours, outside the group). A detected particle is judged on the group's
    /// pixels: a neighbour the fit does not explain may pull its centre, and its detection then
    /// stands as detected.
    fn refit(&self, s: &Subject, members: &[Member]) -> Option<Fitted> {
        let samples = window(self.image, &boxes(members));
        let mut fitted = fit(&samples, members, Free::GuessedRadius)?;
        if self.wanted[s.k].detection.is_none() {
            let own = boxes(&members[..1]);
            fitted.rms = rms_within(&samples, &fitted.residuals(&samples), &own);
        }
        Some(fitted)
    }

    /// What a fit of `members` (the subject's group, perhaps with unknown detections) says of
    /// the subject's particle; `None` where the fit does not explain the pixels or moved a
    /// particle off.
    fn judge(&self, s: &Subject, members: &[Member], fitted: Fitted) -> Option<Measured> {
        let w = &self.wanted[s.k];
        let own = s.members[0];
        // The own particle may vanish where it has no detection: the fit then tells it is gone.
        let may_vanish = |i: usize| {
            if i == 0 {
                w.detection.is_none()
            } else {
                s.hidden.contains(&i)
            }
        };
        // A fit that measures where a detected particle is may leave each member's mismatch
        // (their residuals add); one that decides whether an undetected particle is there at
        // all is held to what a group of lone particles leaves, or a track (a ghost's among
        // them) would go on with its neighbours' light.
        let max_rms = match w.detection {
            Some(_) => self.max_rms * (members.len() as f64).sqrt(),
            None => self.max_rms,
        };
        // A fit that has not settled measures nothing.
        if !fitted.settled || fitted.rms > max_rms || !stayed(&fitted, members, may_vanish) {
            return None;
        }
        let at = fitted.members[0].at;
        if w.detection.is_some() {
            return Some(Measured::Refitted(at));
        }
        let a = fitted.members[0].shape.amplitude;
        let moved = (at.x - own.at.x).hypot(at.y - own.at.y);
        let apart = fitted.members[1..]
            .iter()
            .all(|m| (m.at.x - at.x).hypot(m.at.y - at.y) >= 0.5 * own.shape.radius_px);
        let bright =
            (own.shape.guessed || a >= 0.5 * own.shape.amplitude) && a >= 3.0 * self.max_rms;
        Some(if apart && bright && moved <= own.shape.radius_px {
            Measured::Refitted(at)
        } else {
            Measured::Missing
        })
    }

    /// Wanted particle `k`'s fit group, `own` first (with its id; rectified centre `c`): the
    /// tracked particles whose images may touch its own (at their detections, or where their
    /// tracks put them) and their ids; apart, the detections no track claimed that may touch
    /// it, as guessed discs; and where in the group the particles without a detection are.
    #[allow(clippy::type_complexity)]
    fn neighbours(
        &self,
        k: usize,
        (own, id): (Member, usize),
        c: RectPoint,
    ) -> (Vec<Member>, Vec<usize>, Vec<Member>, Vec<usize>) {
        // The fit sees a box of half-width radius + margin around the particle's centre.
        let reach = (own.shape.radius_px + MARGIN_PX) * std::f64::consts::SQRT_2;
        let own_detection = self.wanted[k].detection;
        let touches = |p: RectPoint, other: &Member| {
            (p.x - c.x).hypot(p.y - c.y) <= reach + other.shape.reach_px()
        };
        let (mut tracked, mut ids, mut unknown) = (vec![own], vec![id], Vec::new());
        for &(p, j) in self.near.grid.near(c.x, c.y, reach + self.near.widest) {
            let other = match self.members.claimed[j] {
                _ if Some(j) == own_detection => continue,
                Some((m, _)) => m,
                None => {
                    let m = guessed(self.image, &self.seen[j], self.edge_px, self.widest_px);
                    if touches(p, &m) {
                        unknown.push(m);
                    }
                    continue;
                }
            };
            if touches(p, &other) {
                tracked.push(other);
                ids.push(j);
            }
        }
        let mut hidden = Vec::new();
        for &(p, j) in self.hidden_grid.near(c.x, c.y, reach + self.near.widest) {
            match self.members.hidden[j] {
                Some(m) if j != k && touches(p, &m) => {
                    hidden.push(tracked.len());
                    tracked.push(m);
                    ids.push(self.seen.len() + j);
                }
                _ => {}
            }
        }
        (tracked, ids, unknown, hidden)
    }
}

/// Whether `at` is at least `margin` pixels inside the image.
fn within(image: ImageView<'_>, at: PixelPoint, margin: f64) -> bool {
    let inside = |c: f64, size: usize| c >= margin && c <= size as f64 - 1.0 - margin;
    inside(at.x, image.width) && inside(at.y, image.height)
}

/// The shape to fit a particle with: its own in this camera, else the one its track learnt in
/// the other camera (both see it from nearly the same distance), a learnt shape before a
/// guessed one.
fn best_known(own: Option<Shape>, other: Option<Shape>) -> Option<Shape> {
    match (own, other) {
        (Some(a), _) if !a.guessed => Some(a),
        (_, Some(b)) if !b.guessed => Some(b),
        (a, b) => a.or(b),
    }
}

/// A detection no track knows, as a fit member: a disc of its diameter (at most `widest_px`
/// in radius) with the camera's edge, at its centroid.
pub(super) fn guessed(image: ImageView<'_>, s: &Seen, edge_px: f64, widest_px: f64) -> Member {
    Member {
        at: s.centroid,
        shape: Shape {
            radius_px: (0.5 * s.diameter_px).min(widest_px),
            edge_px,
            amplitude: image.bilinear(s.centroid).max(1.0),
            guessed: true,
        },
    }
}
