//! Stage 5: velocity by moving least squares over +-M frames (method section 5.5), one vector per
//! 3D track and frame: the window and the fit chosen per track and component from its residuals
//! ([`fit`]), each vector with its 1-sigma errors ([`uncertainty`]), and vectors that stray
//! from their neighbours dropped ([`outliers`]).

use std::cmp::Ordering;

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::config::{check_non_negative, ConfigError};
use crate::detect::Separation;
use crate::geometry::Rectification;
use crate::pipeline::FrameOutput;
use crate::tracks::{Sample, Track3d};

pub mod fit;
pub mod outliers;
pub mod uncertainty;

use fit::{fit_adaptive, fit_line, FitChoice, MotionFit, QuadraticWindow};
use outliers::{neighbour_outliers, NeighbourTest};
use uncertainty::{ScenePool, ScenePrior, UncertaintyBudget};

/// Velocity estimation parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VelocityConfig {
    /// M: frames on each side of the centre in the moving least-squares window (method: 5 on
    /// synthetic data, 2 for the fast wind-tunnel case).
    pub half_window_frames: usize,
    /// Frames each side of the window may lack (method: 0, every frame seen). 1 keeps vectors
    /// for particles hidden for a frame or just appearing, at a small cost in precision.
    pub max_missing_per_side: usize,
    /// Reject a vector whose track does not follow a smooth path: RMS fit residual above
    /// `max_residual_ratio` times the depth noise expected from `disparity_sigma_px`, plus
    /// `residual_floor_m`. A wrong stereo pair or a track that swapped particles jumps in depth.
    /// 0 disables the check (the method).
    pub max_residual_ratio: f64,
    /// Disparity noise assumed by the residual check, pixels.
    pub disparity_sigma_px: f64,
    /// Residual always allowed, metres (covers real accelerations over the window).
    pub residual_floor_m: f64,
    /// Choose each vector's fit from its track (see `kinematics::fit_adaptive`): per component a
    /// quadratic over a window of 2..=M frames each side, or a cubic over the widest, whichever
    /// the track's own residuals predict to be most accurate. Off: the method's quadratic over
    /// +-M.
    pub adaptive_fit: bool,
    /// A window narrower than +-M is allowed (down to +-2) when the particle travels at least
    /// this many pixels within it (along its path): precision then comes from the distance
    /// travelled, not the frame count, and a fast particle that is in view for only a few
    /// frames still gets vectors. Where every window so allowed strays from its quadratic (a
    /// fast-turning path), narrower ones down to +-2 are tried. 0: always +-M (with
    /// `max_missing_per_side`), narrower only where every window is rough.
    pub min_window_travel_px: f64,
    /// With `adaptive_fit`, a straight line from this many frames before the centre to M after
    /// it joins the candidate fits, chosen where the track's own acceleration, lost in its
    /// noise, predicts it to be the most accurate: slow or uniform flow, where a centred window
    /// sees mostly depth noise. No extra latency:
    /// the window still ends M frames after the centre. 0 (the method), or at most M leaves it
    /// out.
    pub line_past_frames: usize,
    /// Each frame's vectors (centred, and causal among themselves) are compared with their
    /// `outlier_neighbours` nearest (in space) and a vector is dropped when a component differs
    /// from the neighbours' median by more than `outlier_threshold` times their median
    /// deviation plus `outlier_noise_fraction` of their median speed, where the neighbours
    /// agree in every component to within `outlier_coherence` of their speed, beyond what
    /// their own stated noise spreads them by (universal outlier detection, Westerweel &
    /// Scarano 2005; [`outliers::neighbour_outliers`]); wherever they stand, a vector off their
    /// median by more than `outlier_threshold` times their speed, spread and its own stated
    /// error together is dropped too. Catches what each track's own smoothness cannot:
    /// a wrong stereo pair or a swapped particle that moves smoothly, but not with the flow.
    /// 0: off (the method).
    pub outlier_neighbours: usize,
    /// Median deviations a component may stray (see `outlier_neighbours`).
    pub outlier_threshold: f64,
    /// Deviation always allowed, a fraction of the neighbours' median speed.
    pub outlier_noise_fraction: f64,
    /// Neighbours are asked only where they agree to within this fraction of their speed
    /// (beyond their noise).
    pub outlier_coherence: f64,
}

impl Default for VelocityConfig {
    fn default() -> Self {
        Self {
            half_window_frames: 5,
            max_missing_per_side: 1,
            max_residual_ratio: 4.0,
            disparity_sigma_px: 0.1,
            residual_floor_m: 0.001,
            adaptive_fit: true,
            min_window_travel_px: 60.0,
            line_past_frames: 15,
            outlier_neighbours: 8,
            outlier_threshold: 4.0,
            outlier_noise_fraction: 0.02,
            outlier_coherence: 0.05,
        }
    }
}

/// The smallest disparity at which a particle's depth counts as measured, pixels: half a
/// pixel of error then moves it by a quarter. Bounds the measurement volume where no depth
/// range is set or learnt (a rig's views overlap out to infinity).
pub const MIN_MEASURED_DISPARITY_PX: f64 = 2.0;

/// A velocity estimate for one track at one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VelocityVector {
    /// The frame the vector describes.
    pub frame_index: u64,
    /// That frame's sensor time, seconds.
    pub t_s: f64,
    /// The 3D track it belongs to.
    pub track_id: u64,
    /// Moving-least-squares smoothed position, world frame, metres.
    pub position_in_world: Point3<f64>,
    /// World frame, metres per second (head motion removed when poses are given).
    pub velocity_in_world: Vector3<f64>,
    /// RMS distance of the track's samples from the fitted path, metres.
    pub rms_residual_m: f64,
    /// 1-sigma error of each velocity component, metres per second: centroid noise carried
    /// through triangulation and the velocity fit, plus the bias the fit expects from the
    /// path's curvature ([`uncertainty`] explains the noise model).
    pub velocity_sigma: Vector3<f64>,
    /// 1-sigma error of each position component, metres.
    pub position_sigma: Vector3<f64>,
}

impl VelocityConfig {
    /// The published method: a quadratic over exactly +-M frames, every frame of the window
    /// seen, no vector rejected.
    pub fn method() -> Self {
        Self {
            max_missing_per_side: 0,
            max_residual_ratio: 0.0,
            adaptive_fit: false,
            min_window_travel_px: 0.0,
            line_past_frames: 0,
            outlier_neighbours: 0,
            ..Self::default()
        }
    }

    /// Refuses values no run can use, naming the key as the config file spells it.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_non_negative(
            "velocity",
            &[
                ("max_residual_ratio", self.max_residual_ratio),
                ("disparity_sigma_px", self.disparity_sigma_px),
                ("residual_floor_m", self.residual_floor_m),
                ("min_window_travel_px", self.min_window_travel_px),
                ("outlier_threshold", self.outlier_threshold),
                ("outlier_noise_fraction", self.outlier_noise_fraction),
                ("outlier_coherence", self.outlier_coherence),
            ],
        )?;
        let bad = |key, reason| ConfigError::invalid("velocity", key, reason);
        // M frames of delay: 100 is over 3 s at 30 Hz, far beyond any useful window, and keeps
        // a client-sent value from overflowing the frame arithmetic or the track memory.
        if !(1..=100).contains(&self.half_window_frames) {
            return Err(bad("half_window_frames", "must be in 1..=100"));
        }
        if self.line_past_frames > 300 {
            return Err(bad("line_past_frames", "must be at most 300"));
        }
        if self.max_missing_per_side >= self.half_window_frames {
            return Err(bad(
                "max_missing_per_side",
                "must be below velocity.half_window_frames (each side needs a sample)",
            ));
        }
        Ok(())
    }
}

/// A centred vector, the fit chosen per component (adaptive fits), and what its window says
/// about the scene (`ScenePool`).
struct Centred {
    vector: VelocityVector,
    choice: Option<[FitChoice; 3]>,
    noise_ratio: Option<f64>,
    /// Its window's cubic term and that estimate's variance, for the scene's pool.
    cubic_term: Option<(Vector3<f64>, Vector3<f64>)>,
}

/// Tracks per parallel task when judging a frame's tracks: a track's fits are small.
const TRACKS_PER_TASK: usize = 32;

/// The narrowest half-window a centred velocity is fitted over, frames: a quadratic through
/// five samples keeps two degrees of freedom to judge its smoothness by.
const MIN_HALF_WINDOW: u64 = 2;

/// One track's vectors for a frame, as [`Velocities::judge`] found them.
struct Judged {
    centred: Option<Result<Centred, ()>>,
    centred_plausible: bool,
    causal: Option<VelocityVector>,
    causal_plausible: bool,
}

/// The velocity stage: its settings, the rig's geometry, and what the scene's vectors have
/// taught it about noise and curvature.
#[derive(Debug, Clone)]
pub(crate) struct Velocities {
    config: VelocityConfig,
    rect: Rectification,
    /// Half the image's longer side, pixels: the most a tracked particle can move per frame.
    reach_px: f64,
    pool: ScenePool,
}

impl Velocities {
    /// A stage for a rig of `rect` with images `width` x `height`.
    pub(crate) fn new(
        config: &VelocityConfig,
        rect: &Rectification,
        width: u32,
        height: u32,
    ) -> Self {
        Self {
            config: config.clone(),
            rect: rect.clone(),
            reach_px: f64::from(width.max(height)) / 2.0,
            pool: ScenePool::default(),
        }
    }

    /// Frame `seq`'s vectors from `tracks` into `out`: the centred ones for the frame M back
    /// (the measurement) and the causal ones for this frame, each judged plausible and against
    /// its neighbours; the kept centred vectors teach the scene's pool.
    pub(crate) fn estimate<'a>(
        &mut self,
        tracks: impl Iterator<Item = &'a Track3d>,
        seq: u64,
        out: &mut FrameOutput,
    ) {
        let tracks: Vec<&Track3d> = tracks.collect();
        // Each track's fits need only the track: spread over the cores, in track order.
        let judged: Vec<Judged> = tracks
            .par_iter()
            .with_min_len(TRACKS_PER_TASK)
            .map(|track| self.judge(track, seq))
            .collect();
        let mut centred = Vec::new();
        for j in judged {
            match j.centred {
                Some(Ok(found)) if j.centred_plausible => centred.push(found),
                Some(Ok(_)) => out.stats.implausible += 1,
                Some(Err(())) => out.stats.rejected += 1,
                None => {}
            }
            match j.causal {
                Some(v) if j.causal_plausible => out.causal_vectors.push(v),
                Some(_) => out.stats.implausible += 1,
                None => {}
            }
        }
        // Live causal vectors are judged too: the holograms should not show what the
        // recording will drop.
        let test = self.neighbour_test();
        let (causal_outliers, centred_outliers) = rayon::join(
            || outliers_among(out.causal_vectors.iter(), &test),
            || outliers_among(centred.iter().map(|c| &c.vector), &test),
        );
        let mut causal_outliers = causal_outliers.into_iter();
        out.causal_vectors
            .retain(|_| !causal_outliers.next().unwrap_or(false));
        self.keep_centred(centred, &centred_outliers, out);
    }

    /// One track's centred and causal vectors for frame `seq`, each with whether it is
    /// plausible.
    fn judge(&self, track: &Track3d, seq: u64) -> Judged {
        let centred = self.centred_vector(track, seq);
        let causal = self.causal_vector(track, seq);
        Judged {
            centred_plausible: matches!(&centred, Some(Ok(c)) if self.is_plausible(&c.vector, track)),
            causal_plausible: causal.as_ref().is_some_and(|v| self.is_plausible(v, track)),
            centred,
            causal,
        }
    }

    /// Keeps the centred vectors that do not stray from their neighbours (`outliers`, index
    /// for index), counting their fits, and learns from them after the frame, so a frame's
    /// sigmas do not depend on the order of its tracks.
    fn keep_centred(&mut self, centred: Vec<Centred>, outliers: &[bool], out: &mut FrameOutput) {
        let m = self.config.half_window_frames;
        let mut learnt = false;
        for (found, &outlier) in centred.into_iter().zip(outliers) {
            if outlier {
                out.stats.outliers += 1;
                continue;
            }
            if let Some(ratio) = found.noise_ratio {
                self.pool.add_noise(ratio);
            }
            if let Some((term, variance)) = found.cubic_term {
                self.pool.add_cubic_term(term, variance);
            }
            learnt = true;
            out.vectors.push(found.vector);
            for c in found.choice.iter().flatten() {
                if c.order == 1 {
                    out.stats.fit_components_line += 1;
                } else if c.order > 2 {
                    out.stats.fit_components_cubic += 1;
                } else if usize::from(c.half_window_frames) < m {
                    out.stats.fit_components_narrower += 1;
                }
            }
        }
        if learnt {
            self.pool.refresh();
        }
    }

    fn neighbour_test(&self) -> NeighbourTest {
        let v = &self.config;
        NeighbourTest {
            neighbours: v.outlier_neighbours,
            threshold: v.outlier_threshold,
            noise_fraction: v.outlier_noise_fraction,
            coherence: v.outlier_coherence,
        }
    }

    /// Fit residual above which a track is judged rough, for a sample at `depth_m`; `None` when
    /// the check is off.
    fn max_residual_m(&self, depth_m: f64) -> Option<f64> {
        let v = &self.config;
        (v.max_residual_ratio > 0.0).then(|| {
            v.max_residual_ratio * self.rect.depth_sigma_m(depth_m, v.disparity_sigma_px)
                + v.residual_floor_m
        })
    }

    /// Whether a centred window strays from its quadratic more than noise explains, judged
    /// along the line of sight (depth noise, large) and across it (centroid noise, small)
    /// separately: a track that swapped to a neighbouring particle jumps sideways by a few
    /// pixels, which a single limit set by the depth noise would let through.
    fn is_rough(&self, window: &[&Sample], fit: &QuadraticWindow, depth_m: f64) -> bool {
        let v = &self.config;
        if v.max_residual_ratio <= 0.0 {
            return false;
        }
        let (mut along_sq, mut across_sq) = (0.0, 0.0);
        for (s, r) in window.iter().zip(fit.residuals()) {
            let (along, across) = s.along_and_across_sq(&r);
            along_sq += along * along;
            across_sq += across;
        }
        let n = window.len() as f64;
        let along_limit = v.max_residual_ratio
            * self.rect.depth_sigma_m(depth_m, v.disparity_sigma_px)
            + v.residual_floor_m;
        // Two directions across the line of sight, each with the centroid noise.
        let across_limit =
            v.max_residual_ratio * std::f64::consts::SQRT_2 * depth_m * v.disparity_sigma_px
                / self.rect.focal_px
                + v.residual_floor_m;
        (along_sq / n).sqrt() > along_limit || (across_sq / n).sqrt() > across_limit
    }

    /// Whether a vector can be a measurement at all, whatever the config: a wearer must never
    /// see, and a recording never keep, an arrow tens of metres away at hundreds of m/s.
    /// - Inside the measurement volume: its particle's depth is resolved, seen at a disparity of
    ///   at least `MIN_MEASURED_DISPARITY_PX` (beyond, half a pixel of matching error moves the
    ///   depth by more than a quarter of itself: a match there says little more than "far"),
    ///   by the median of the track's samples around the vector (one sample's disparity is off
    ///   by its matching error, and a far particle's by a large part of itself).
    /// - No faster than a tracked particle can move: over one frame interval its step must
    ///   move the particle across the image, or change its disparity, by at most half the
    ///   image's longer side (a particle must stay in view for the frames its velocity is
    ///   fitted over, and each camera can contribute that much to the disparity).
    fn is_plausible(&self, v: &VelocityVector, track: &Track3d) -> bool {
        let Some(at) = track
            .samples
            .iter()
            .find(|s| s.frame_index == v.frame_index)
        else {
            return true;
        };
        let focal_px = self.rect.focal_px;
        let focal_baseline = focal_px * self.rect.baseline_m;
        let farthest_m = focal_baseline / MIN_MEASURED_DISPARITY_PX;
        if !resolved_within(
            track,
            at,
            2 * self.config.half_window_frames as u64,
            farthest_m,
        ) {
            return false;
        }
        let depth = at.depth_m;
        let (first, last) = match (track.samples.front(), track.samples.back()) {
            (Some(first), Some(last)) if last.seq > first.seq => (first, last),
            _ => return true,
        };
        let frame_interval_s = (last.t_s - first.t_s) / (last.seq - first.seq) as f64;
        let reach_px = self.reach_px;
        let step = v.velocity_in_world * frame_interval_s;
        let (along, across_sq) = at.along_and_across_sq(&step);
        across_sq.sqrt() * focal_px / depth <= reach_px
            && along.abs() * focal_baseline / (depth * depth) <= 2.0 * reach_px
    }

    /// The causal estimate for the newest frame: a straight line through the track's clean
    /// samples of the last `2M + 1` frames, evaluated at the newest. The track must be seen in
    /// the newest frame and have at least `M + 1` clean samples. A line beats the quadratic
    /// here: an end-point derivative of a quadratic amplifies noise about six-fold, and young
    /// tracks (few samples) would give the worst vectors. Rough tracks get no causal vector (not
    /// counted as rejected: their centred check comes later).
    fn causal_vector(&self, track: &Track3d, seq: u64) -> Option<VelocityVector> {
        let newest = track.samples.back().filter(|s| s.seq == seq)?;
        let m = self.config.half_window_frames;
        let recent = |worst: Separation| -> Vec<(f64, Point3<f64>)> {
            track
                .samples
                .iter()
                .filter(|s| s.separation <= worst && seq - s.seq <= 2 * m as u64)
                .map(|s| (s.t_s, s.point_in_world))
                .collect()
        };
        let mut points = recent(Separation::Clear);
        if points.len() < m + 1 {
            points = recent(Separation::Fitted);
        }
        if points.len() < m + 1 {
            return None;
        }
        let fit = fit_line(&points, newest.t_s)?;
        if self
            .max_residual_m(newest.depth_m)
            .is_some_and(|max| fit.rms_residual > max)
        {
            return None;
        }
        Some(vector_at(
            track,
            newest,
            &fit,
            self.scene_prior(newest).as_ref(),
        ))
    }

    /// A sample's noise variance per world component for a unit disparity variance: the
    /// disparity error moves it along the left camera's line of sight by `z^2 / (f b)` per
    /// pixel, and across it each camera's centroid error (disparity's over sqrt 2), averaged
    /// over the two cameras, by `z / (2 f)` per pixel.
    fn noise_unit(&self, sample: &Sample) -> Vector3<f64> {
        let focal_px = self.rect.focal_px;
        let z = sample.depth_m;
        let along = z * z / (focal_px * self.rect.baseline_m);
        let across = z / (2.0 * focal_px);
        let sight = (sample.point_in_world - sample.camera_in_world)
            .try_normalize(1e-12)
            .unwrap_or_else(Vector3::z);
        sight.map(|s| along * along * s * s + across * across * (1.0 - s * s))
    }

    /// What the scene's pool says about a window centred on `sample`: its noise scaled to where
    /// `sample` sits (`noise_unit`), for `UncertaintyBudget::sigmas`.
    fn scene_prior(&self, sample: &Sample) -> Option<ScenePrior> {
        self.pool.noise_variance.map(|k| ScenePrior {
            noise_variance: self.noise_unit(sample) * k,
            noise_dof: ScenePool::WEIGHT_DOF,
            cubic_term_spread: self.pool.cubic_term_spread,
        })
    }

    /// What a window's residuals say the disparity noise variance is (see `noise_unit`).
    fn noise_ratio(&self, error: &UncertaintyBudget, sample: &Sample) -> Option<f64> {
        // Fewer residuals than this say too little to teach the pool.
        const MIN_DOF: f64 = 4.0;
        (error.noise_dof >= MIN_DOF)
            .then(|| error.noise_variance.sum() / self.noise_unit(sample).sum())
    }

    /// The centred estimate for the frame `M` frames back, if the track's window supports one;
    /// `Err` if rejected as rough. The centre frame must be seen, and each side of a window of
    /// `+-w` frames may miss at most `max_missing_per_side` frames (to a gap, or to the track's
    /// start or end; a narrower window may miss none), and as many again seen by one camera
    /// only ([`Self::fills`]). `w` is M, or narrower down to 2 where the particle travels
    /// `min_window_travel_px` within it or every wider window is rough; with `adaptive_fit` the
    /// fit is chosen per component among the windows the track supports (returned with the
    /// vector).
    fn centred_vector(&self, track: &Track3d, seq: u64) -> Option<Result<Centred, ()>> {
        let velocity = &self.config;
        let m = velocity.half_window_frames as u64;
        let centre_seq = seq.checked_sub(m)?;
        // Samples only cut out of overlapping particles keep the track's identity but do not
        // enter the fit: their centroids are biased. Samples separated by a trustworthy spot fit
        // stand in only where the clear ones cannot carry a fit, so a vector the clear samples
        // give is not diluted. The fit needs no sample at the centre itself, so a particle
        // hidden in an overlap at the centre frame still gets a vector from its neighbours in
        // time.
        let centre = track.samples.iter().find(|s| s.seq == centre_seq)?;
        let (mut windows, mut any_supported) =
            self.candidate_windows(track, centre, Separation::Clear);
        let fitted_in_window = || {
            track
                .samples
                .iter()
                .any(|s| s.separation == Separation::Fitted && s.seq.abs_diff(centre_seq) <= m)
        };
        let mut worst = Separation::Clear;
        if !any_supported && fitted_in_window() {
            worst = Separation::Fitted;
            (windows, any_supported) = self.candidate_windows(track, centre, worst);
        }
        if windows.is_empty() {
            return any_supported.then_some(Err(()));
        }
        let (fit, choice) = if velocity.adaptive_fit {
            let past = self.past_window(track, centre, worst, windows.last());
            let adaptive = fit_adaptive(&windows, past.as_ref(), centre.t_s)?;
            (adaptive.fit, Some(adaptive.choice))
        } else {
            (windows.last()?.motion()?, None)
        };
        let prior = self.scene_prior(centre);
        Some(Ok(Centred {
            vector: vector_at(track, centre, &fit, prior.as_ref()),
            choice,
            noise_ratio: self.noise_ratio(&fit.error, centre),
            cubic_term: (fit.error.cubic_term_gain > 0.0).then(|| {
                let noise = fit.error.pooled_noise(prior.as_ref());
                (fit.error.cubic_term, fit.error.cubic_term_variance(&noise))
            }),
        }))
    }

    /// The velocity windows a track's samples (those separated at least as well as `worst`)
    /// support around `centre`, narrowest first, leaving out rough ones; and whether any window
    /// was supported at all (all rough: the track is rejected, not merely short).
    fn candidate_windows(
        &self,
        track: &Track3d,
        centre: &Sample,
        worst: Separation,
    ) -> (Vec<QuadraticWindow>, bool) {
        let m = self.config.half_window_frames as u64;
        let usable_within = |w: u64| {
            track
                .samples
                .iter()
                .filter(move |s| usable(s, worst) && s.seq.abs_diff(centre.seq) <= w)
                .collect::<Vec<&Sample>>()
        };
        // Fitted samples enter full windows only: in a narrowed one the few samples cannot show
        // a fit that swapped two crossing particles.
        let narrowest = if worst == Separation::Clear {
            self.narrowest_window(&usable_within(m), m)
        } else {
            m
        };
        // Candidate windows, narrowest first; a window whose samples stray from a smooth path
        // (a swapped particle, a wrong stereo pair) is left out, and narrower ones that end
        // before the stray sample may still serve.
        let mut windows = Vec::new();
        let mut any_supported = false;
        for w in narrowest..=m {
            match self.window_of(usable_within(w), centre, w) {
                Some(Ok(window)) => windows.push(window),
                Some(Err(())) => any_supported = true,
                None => {}
            }
        }
        any_supported |= !windows.is_empty();
        // Every window the particle's travel allows strays from its quadratic: a path that
        // turns faster than a quadratic follows over them (a vortex), or a stray sample in all
        // of them. Narrower clean windows follow the one and end before the other.
        if windows.is_empty() && any_supported && worst == Separation::Clear {
            for w in MIN_HALF_WINDOW.min(narrowest)..narrowest {
                if let Some(Ok(window)) = self.window_of(usable_within(w), centre, w) {
                    windows.push(window);
                }
            }
        }
        (windows, any_supported)
    }

    /// The half-window `w` fitted around `centre` through `samples` (those within it): `None`
    /// where they do not fill it, `Err` where they stray from a smooth path.
    fn window_of(
        &self,
        samples: Vec<&Sample>,
        centre: &Sample,
        w: u64,
    ) -> Option<Result<QuadraticWindow, ()>> {
        // A narrowed window is complete: it has few samples to spare, and a quadratic through
        // three or four of them says nothing about the track's smoothness.
        let needed = if w < self.config.half_window_frames as u64 {
            w
        } else {
            w.saturating_sub(self.config.max_missing_per_side as u64)
                .max(1)
        };
        if !Self::fills(&samples, centre.seq, [needed; 2], w.saturating_sub(needed)) {
            return None;
        }
        // Ill-posed only without distinct sample times, which the counts above exclude.
        let window = fit_window(w as usize, &samples, centre.t_s)
            .filter(|window| !self.is_rough(&samples, window, centre.depth_m));
        Some(window.ok_or(()))
    }

    /// Whether a window's samples fill it: `needed` samples before and after the centre, of
    /// which at most `allowance` (the frames the window may miss in both images) seen by one
    /// camera only (a frame missing in one image is worth more than one missing in both, but
    /// its depth is not measured), and its depth measured ([`depth_measured`]).
    fn fills(samples: &[&Sample], centre_seq: u64, needed: [u64; 2], allowance: u64) -> bool {
        let count = |side: Ordering, by_both: bool| {
            samples
                .iter()
                .filter(|s| s.seq.cmp(&centre_seq) == side && (!by_both || s.seen_from.is_none()))
                .count() as u64
        };
        [Ordering::Less, Ordering::Greater]
            .into_iter()
            .zip(needed)
            .all(|(side, n)| count(side, false) >= n && count(side, true) + allowance >= n)
            && depth_measured(samples, centre_seq)
    }

    /// The window for a line reaching `line_past_frames` before `centre` and M after it, where
    /// the track's samples (separated at least as well as `worst`) fill it (the full +-M window
    /// `widest` is supported, and at most `max_missing_per_side` frames before the centre are
    /// missing) and do not stray from a smooth path.
    fn past_window(
        &self,
        track: &Track3d,
        centre: &Sample,
        worst: Separation,
        widest: Option<&QuadraticWindow>,
    ) -> Option<QuadraticWindow> {
        let velocity = &self.config;
        let (m, past) = (velocity.half_window_frames, velocity.line_past_frames);
        if past <= m || widest?.half_window_frames < m {
            return None;
        }
        let samples: Vec<&Sample> = track
            .samples
            .iter()
            .filter(|s| {
                usable(s, worst)
                    && s.seq + past as u64 >= centre.seq
                    && s.seq <= centre.seq + m as u64
            })
            .collect();
        let missing = velocity.max_missing_per_side;
        let needed = [past.saturating_sub(missing), m.saturating_sub(missing)];
        if !Self::fills(
            &samples,
            centre.seq,
            needed.map(|n| n as u64),
            missing as u64,
        ) {
            return None;
        }
        let window = fit_window(m, &samples, centre.t_s)?;
        (!self.is_rough(&samples, &window, centre.depth_m)).then_some(window)
    }

    /// The narrowest half-window (2..=m) a track's samples may be fitted over: the particle must
    /// travel `min_window_travel_px` within it, judged from its mean image speed over `samples`
    /// along its path (a vortex's particle comes back near where it was: the chord would say
    /// it barely moved).
    fn narrowest_window(&self, samples: &[&Sample], m: u64) -> u64 {
        let travel_px = self.config.min_window_travel_px;
        let (Some(first), Some(last)) = (samples.first(), samples.last()) else {
            return m;
        };
        if travel_px <= 0.0 || last.seq <= first.seq {
            return m;
        }
        let path_px: f64 = samples
            .windows(2)
            .map(|p| {
                (p[1].left_rect.x - p[0].left_rect.x).hypot(p[1].left_rect.y - p[0].left_rect.y)
            })
            .sum();
        let speed_px = path_px / (last.seq - first.seq) as f64;
        let frames_each_side = (travel_px / (2.0 * speed_px)).ceil();
        if frames_each_side.is_finite() {
            (frames_each_side as u64).clamp(MIN_HALF_WINDOW.min(m), m)
        } else {
            m
        }
    }
}

/// Whether `track`'s particle is seen nearer than `farthest_m` (and in front of the rig) around
/// sample `at`: by the median depth of its samples within `reach` frames of it that both
/// cameras measured (a sample one camera hid has only its predicted depth), or by `at`'s own
/// where there are none. Most tracks lie well inside: their samples are not sorted.
fn resolved_within(track: &Track3d, at: &Sample, reach: u64, farthest_m: f64) -> bool {
    let inside = |depth: f64| depth > 0.0 && depth <= farthest_m;
    let depths = track
        .samples
        .iter()
        .filter(|s| s.seen_from.is_none() && s.seq.abs_diff(at.seq) <= reach)
        .map(|s| s.depth_m);
    let (mut seen, mut all_inside) = (0, true);
    for depth in depths.clone() {
        seen += 1;
        all_inside &= inside(depth);
    }
    match (seen, all_inside) {
        (0, _) => inside(at.depth_m),
        (_, true) => true,
        _ => inside(crate::spatial::median(&mut depths.collect::<Vec<_>>())),
    }
}

/// Whether a sample enters fits whose samples are separated at least as well as `worst`: one
/// both cameras measured that well, or one only the camera that saw it measured that well
/// (across its line of sight).
fn usable(s: &Sample, worst: Separation) -> bool {
    s.separation <= worst || s.seen_from.is_some_and(|v| v.separation <= worst)
}

/// Whether a window's samples measure its depth: a quadratic's worth of samples seen by both
/// cameras, at least one each side of the centre (or at it), so the samples seen by one
/// camera only fill in between rather than extrapolate.
fn depth_measured(samples: &[&Sample], centre_seq: u64) -> bool {
    let both = || samples.iter().filter(|s| s.seen_from.is_none());
    both().count() >= 3
        && both().any(|s| s.seq <= centre_seq)
        && both().any(|s| s.seq >= centre_seq)
}

/// A window's quadratic, the samples one camera hid measured across the other's line of
/// sight only ([`QuadraticWindow::with_sights`]).
fn fit_window(
    half_window_frames: usize,
    samples: &[&Sample],
    t_eval_s: f64,
) -> Option<QuadraticWindow> {
    let points = samples.iter().map(|s| (s.t_s, s.point_in_world)).collect();
    // Most windows have every sample seen by both cameras: they need no sights.
    if samples.iter().all(|s| s.seen_from.is_none()) {
        return QuadraticWindow::new(half_window_frames, points, t_eval_s);
    }
    let sights: Vec<_> = samples
        .iter()
        .map(|s| s.seen_from.map(|v| v.camera_in_world))
        .collect();
    QuadraticWindow::with_sights(half_window_frames, points, &sights, t_eval_s)
}

/// The vector a fit gives for `track` at `sample`, its sigmas from the fit and the scene prior.
fn vector_at(
    track: &Track3d,
    sample: &Sample,
    fit: &MotionFit,
    prior: Option<&ScenePrior>,
) -> VelocityVector {
    let (velocity_sigma, position_sigma) = fit.error.sigmas(prior);
    VelocityVector {
        frame_index: sample.frame_index,
        t_s: sample.t_s,
        track_id: track.id,
        position_in_world: fit.position,
        velocity_in_world: fit.velocity,
        rms_residual_m: fit.rms_residual,
        velocity_sigma,
        position_sigma,
    }
}

/// Which of a frame's vectors stray from their neighbours (see `kinematics::neighbour_outliers`).
fn outliers_among<'a>(
    vectors: impl Iterator<Item = &'a VelocityVector>,
    test: &NeighbourTest,
) -> Vec<bool> {
    let vectors: Vec<_> = vectors
        .map(|v| (v.position_in_world, v.velocity_in_world, v.velocity_sigma))
        .collect();
    neighbour_outliers(&vectors, test)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::RectPoint;
    use crate::synth::{Scenario, ScenarioSpec};
    use crate::tracks::Sight;

    /// Eleven frames of a particle moving at 0.1 m/s along x half a metre from the left
    /// camera: seen by both cameras but in frames `hidden` (seen by the left one only, and
    /// placed 1 cm off along its line of sight) and `missing` (seen by neither).
    fn track(hidden: &[u64], missing: &[u64]) -> Track3d {
        let path = |t: f64| Point3::new(-0.02 + 0.1 * t, 0.01, 0.5);
        let samples = (1..=11)
            .filter(|seq| !missing.contains(seq))
            .map(|seq| {
                let t_s = seq as f64 / 30.0;
                let mut sample = Sample {
                    seq,
                    frame_index: seq,
                    t_s,
                    point_in_world: path(t_s),
                    depth_m: 0.5,
                    separation: Separation::Clear,
                    left_rect: RectPoint::default(),
                    camera_in_world: Point3::origin(),
                    seen_from: None,
                };
                if hidden.contains(&seq) {
                    sample.point_in_world += path(t_s).coords.normalize() * 0.01;
                    sample.separation = Separation::Hidden;
                    sample.seen_from = Some(Sight {
                        camera_in_world: Point3::origin(),
                        separation: Separation::Clear,
                    });
                }
                sample
            })
            .collect();
        Track3d {
            samples,
            ..Track3d::new(1, 1)
        }
    }

    #[test]
    fn frames_one_camera_hid_fill_a_window_as_far_as_the_allowance_goes() {
        let rect = Rectification::new(&ScenarioSpec::new(Scenario::Flume).rig).expect("rectifies");
        let velocities = Velocities::new(&VelocityConfig::default(), &rect, 640, 480);
        let at_centre = |t: &Track3d| velocities.centred_vector(t, 11).map(Result::ok);
        // Two frames hidden before the centre (one more than may be missing) still measure
        // the velocity, exactly: across the line of sight they are measured.
        let v = at_centre(&track(&[2, 4], &[])).flatten().expect("a vector");
        let error = (v.vector.velocity_in_world - Vector3::new(0.1, 0.0, 0.0)).norm();
        assert!(error < 1e-9, "{error}");
        // Three hidden, or two missing in both images, are more than one side may lack.
        assert!(at_centre(&track(&[2, 3, 4], &[])).is_none());
        assert!(at_centre(&track(&[], &[2, 4])).is_none());
        // One missing and one hidden is within the allowance.
        assert!(at_centre(&track(&[4], &[2])).flatten().is_some());
    }

    /// Frames 1 to 11 of a particle on a circle half a metre from the left camera, turning
    /// `turn` radians a frame and moving `step_px` pixels a frame in the image.
    fn circling(rect: &Rectification, turn: f64, step_px: f64) -> (Track3d, Vector3<f64>) {
        let (depth, frame_s) = (0.5, 1.0 / 30.0);
        let radius = step_px / turn * depth / rect.focal_px;
        let rate = turn / frame_s;
        let at = |t: f64| Point3::new(radius * (rate * t).cos(), radius * (rate * t).sin(), depth);
        let samples = (1..=11)
            .map(|seq| {
                let t_s = seq as f64 * frame_s;
                let p = at(t_s);
                Sample {
                    seq,
                    frame_index: seq,
                    t_s,
                    point_in_world: p,
                    depth_m: depth,
                    separation: Separation::Clear,
                    left_rect: RectPoint {
                        x: rect.focal_px * p.x / depth,
                        y: rect.focal_px * p.y / depth,
                    },
                    camera_in_world: Point3::origin(),
                    seen_from: None,
                }
            })
            .collect();
        let t_centre = 6.0 * frame_s;
        let truth = Vector3::new(
            -radius * rate * (rate * t_centre).sin(),
            radius * rate * (rate * t_centre).cos(),
            0.0,
        );
        let track = Track3d {
            samples,
            ..Track3d::new(1, 1)
        };
        (track, truth)
    }

    #[test]
    fn a_path_turning_faster_than_its_travel_windows_follow_is_measured_over_a_narrower_one() {
        let rect = Rectification::new(&ScenarioSpec::new(Scenario::Flume).rig).expect("rectifies");
        let velocities = Velocities::new(&VelocityConfig::default(), &rect, 640, 480);
        // 14 px a frame: the travel asks for +-3 frames at least, over which a quadratic
        // cannot follow a path turning half a radian a frame.
        let (track, truth) = circling(&rect, 0.5, 14.0);
        let centre = &track.samples[5];
        let m = velocities.config.half_window_frames as u64;
        let all: Vec<&Sample> = track.samples.iter().collect();
        assert_eq!(velocities.narrowest_window(&all, m), 3);
        for w in 3..=m {
            let within: Vec<&Sample> = track
                .samples
                .iter()
                .filter(|s| s.seq.abs_diff(centre.seq) <= w)
                .collect();
            assert!(matches!(
                velocities.window_of(within, centre, w),
                Some(Err(()))
            ));
        }
        let found = velocities.centred_vector(&track, 11).expect("a centre");
        let v = found.expect("measured, not rejected as rough").vector;
        let error = (v.velocity_in_world - truth).norm() / truth.norm();
        assert!(error < 0.01, "{error}");
    }
}
