//! Which particles one camera's shake fits, and what the fit says of each: every predicted
//! particle's group (its own image and the tracked ones that may touch it), all groups measured
//! at once in sweeps ([`Sweep`]), and each particle judged as a fit of its group would be.

use super::sweep::Sweep;
use super::{
    best_known, farther_than, stayed, Fitted, Measured, Member, Neighbourhood, Seen, Shape, Wanted,
    MARGIN_PX,
};
use crate::geometry::{PixelPoint, RectPoint};
use crate::spatial::{PointGrid, GRID_CELL_PX};
use crate::ImageView;

/// One camera's particles as fit members: per detection, the track's member that claimed it;
/// per wanted particle without a detection, its member at its prediction.
pub(super) struct Members {
    claimed: Vec<Option<Member>>,
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
                members.claimed[i] = Some(Member { at, shape });
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
/// the particles without a detection are, and the detections no track knows that may touch it
/// (by id).
struct Subject {
    k: usize,
    members: Vec<Member>,
    ids: Vec<usize>,
    hidden: Vec<usize>,
    unknown: Vec<(usize, Member)>,
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

    /// Every wanted particle measured among its neighbours (`None`: not fitted): all of one
    /// camera's fitted particles and their tracked neighbours in one sweep; those whose verdict
    /// that does not give, again with the detections no track knows near them (most are
    /// fragments of a tracked particle's image, and would take its light where it is clear).
    pub(super) fn measure_all(&self) -> Vec<Option<Measured>> {
        let subjects: Vec<Option<Subject>> =
            (0..self.wanted.len()).map(|k| self.subject(k)).collect();
        let all: Vec<&Subject> = subjects.iter().flatten().collect();
        let mut measured = vec![None; subjects.len()];
        let first = self.sweep_of(&all, false, None);
        for s in &all {
            measured[s.k] = self.judge_swept(s, &first, false);
        }
        let again: Vec<&Subject> = all
            .into_iter()
            .filter(|s| measured[s.k].is_none() && !s.unknown.is_empty())
            .collect();
        let second = self.sweep_of(&again, true, Some(&first));
        for s in &again {
            measured[s.k] = self.judge_swept(s, &second, true);
        }
        measured
    }

    /// One sweep of `subjects`' groups (with the detections no track knows where
    /// `with_unknown`). Their tracked neighbours that an `earlier` sweep measured (fitted and
    /// settled), or whose detections were fitted already, are held where those fits left
    /// them: only the subjects, their other tracked neighbours and the detections no track
    /// knows are fitted.
    fn sweep_of(
        &self,
        subjects: &[&Subject],
        with_unknown: bool,
        earlier: Option<&Sweep>,
    ) -> Sweep {
        let mut subject_ids = vec![false; self.seen.len() + self.wanted.len()];
        for s in subjects {
            subject_ids[s.ids[0]] = true;
        }
        // A tracked particle whose detection was fitted already (parted with the tracks'
        // shapes) is measured where that fit put it.
        let parted = |id: usize, m: &Member| {
            let fitted =
                id < self.seen.len() && self.seen[id].fitted && self.members.claimed[id].is_some();
            (fitted && !subject_ids[id]).then(|| Member {
                at: self.seen[id].centroid,
                ..*m
            })
        };
        let measured = |id: usize| {
            let e = earlier.filter(|_| !subject_ids[id])?;
            let i = e.element(id).filter(|&i| e.fitted(i) && e.settled(i))?;
            Some(e.member(i))
        };
        let mut sweep = Sweep::default();
        for s in subjects {
            for (&id, m) in self.group_of(s, with_unknown) {
                match measured(id).or_else(|| parted(id, m)) {
                    Some(member) => sweep.hold(id, member),
                    None => sweep.add(id, *m),
                }
            }
        }
        sweep.run(self.image);
        sweep
    }

    /// A subject's group: its own particle and tracked neighbours, with the detections no
    /// track knows where `with_unknown`, by id.
    fn group_of<'s>(
        &self,
        s: &'s Subject,
        with_unknown: bool,
    ) -> impl Iterator<Item = (&'s usize, &'s Member)> {
        let unknown: &[(usize, Member)] = if with_unknown { &s.unknown } else { &[] };
        let tracked = s.ids.iter().zip(&s.members);
        tracked.chain(unknown.iter().map(|(id, m)| (id, m)))
    }

    /// What a sweep says of a subject's particle, judged as a fit of its group would be: on
    /// the residual its own pixels are left with, its group's steps settled.
    fn judge_swept(&self, s: &Subject, sweep: &Sweep, with_unknown: bool) -> Option<Measured> {
        let (elements, seeds): (Vec<Option<usize>>, Vec<Member>) = self
            .group_of(s, with_unknown)
            .map(|(&id, m)| (sweep.element(id), *m))
            .unzip();
        let elements: Vec<usize> = elements.into_iter().collect::<Option<_>>()?;
        let own = elements[0];
        if !sweep.fitted(own) {
            return None;
        }
        let fitted = Fitted {
            members: elements.iter().map(|&i| sweep.member(i)).collect(),
            rms: sweep.rms_on(own),
            settled: elements.iter().all(|&i| sweep.settled(i)),
        };
        self.judge(s, &seeds, fitted)
    }

    /// Wanted particle `k`'s fit, `None` where it is not fitted (no shape known, or a
    /// detection standing alone or fitted already, with no hidden particle near: its centre is
    /// measured as detected). A clear detection that touches
    /// another (parted from it at a dip between their peaks) is fitted: the neighbour's light
    /// in its region pulls its centroid.
    fn subject(&self, k: usize) -> Option<Subject> {
        let w = &self.wanted[k];
        let (own, alone, c, id) = match w.detection {
            Some(i) => {
                let own = self.members.claimed[i]?;
                (own, self.near.alone(self.seen, i), self.seen[i].rect, i)
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
        let fitted = w.detection.is_some_and(|i| self.seen[i].fitted);
        if (alone || fitted) && hidden.is_empty() {
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
    ) -> (Vec<Member>, Vec<usize>, Vec<(usize, Member)>, Vec<usize>) {
        // The fit sees a box of half-width radius + margin around the particle's centre.
        let reach = (own.shape.radius_px + MARGIN_PX) * std::f64::consts::SQRT_2;
        let own_detection = self.wanted[k].detection;
        let touches = |p: RectPoint, other: &Member| {
            !farther_than((p.x - c.x, p.y - c.y), reach + other.shape.reach_px())
        };
        let (mut tracked, mut ids, mut unknown) = (vec![own], vec![id], Vec::new());
        for &(p, j) in self.near.grid.near(c.x, c.y, reach + self.near.widest) {
            let other = match self.members.claimed[j] {
                _ if Some(j) == own_detection => continue,
                Some(m) => m,
                None => {
                    let m = guessed(self.image, &self.seen[j], self.edge_px, self.widest_px);
                    if touches(p, &m) {
                        unknown.push((j, m));
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
