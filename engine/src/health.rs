//! A run's health: what it settled on, its figures, and in words what they say cannot be
//! trusted (every run without vectors says why).

use crate::pipeline::{FrameStats, Pipeline, PipelineConfig};
use crate::stereo::StereoSearch;

/// Totals over a processing run.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RunTotals {
    /// Frames pushed.
    pub frames: usize,
    /// The frames' statistics, summed.
    pub counts: FrameStats,
    /// Time spent inside `Pipeline::push`, seconds.
    pub pipeline_s: f64,
    /// The stereo search the pipeline settled on.
    pub stereo_search: Option<StereoSearch>,
    /// The last search it narrowed to where the tracks were (`stereo.learn_depth_range`).
    pub learnt_search: Option<StereoSearch>,
}

/// A run's health figures (see [`RunTotals::health`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct HealthFigures {
    /// Detections per image.
    pub detections_per_image: f64,
    /// Of all detections, those continuing a track from an earlier frame.
    pub linked_fraction: f64,
    /// Stereo candidates per left particle that had at least one.
    pub stereo_candidates_per_particle: f64,
    /// Of left detections, those matched in the right image.
    pub matched_fraction: f64,
    /// Of matched particles, those given a centred velocity.
    pub velocity_fraction: f64,
}

impl RunTotals {
    /// Adds one frame's statistics and the seconds `Pipeline::push` took on it.
    pub fn add(&mut self, s: &FrameStats, pipeline_s: f64) {
        self.frames += 1;
        self.counts += s;
        self.pipeline_s += pipeline_s;
    }

    /// Empty totals that remember the stereo search `pipeline` settled on.
    pub fn for_pipeline(pipeline: &Pipeline) -> Self {
        Self {
            stereo_search: Some(*pipeline.stereo_search()),
            ..Default::default()
        }
    }

    /// The run's health figures so far.
    pub fn figures(&self) -> HealthFigures {
        let detections = self.counts.detections_left + self.counts.detections_right;
        HealthFigures {
            detections_per_image: ratio(detections, 2 * self.frames),
            linked_fraction: ratio(
                self.counts.linked_left + self.counts.linked_right,
                detections,
            ),
            stereo_candidates_per_particle: ratio(
                self.counts.stereo_candidates,
                self.counts.left_with_candidates,
            ),
            matched_fraction: ratio(self.counts.matches, self.counts.detections_left),
            velocity_fraction: ratio(self.counts.vectors, self.counts.matches),
        }
    }

    /// What a run settled on, how healthy it was, and in words what its figures say cannot be
    /// trusted; a run that gave no vectors always gets a warning saying why.
    pub fn health(&self, config: &PipelineConfig) -> RunHealth {
        let words = Words::new(self, config);
        RunHealth {
            settled: words.settled(),
            summary: words.summary(),
            warnings: words.warnings(),
        }
    }
}

/// A run's figures and settings, put into words.
struct Words<'a> {
    totals: &'a RunTotals,
    config: &'a PipelineConfig,
    figures: HealthFigures,
    /// The stereo search in words.
    search: String,
    /// The velocity windows in words.
    windows: String,
    /// The full window and the shortest a fast particle may have.
    window: usize,
    shortest_window: usize,
}

impl<'a> Words<'a> {
    fn new(totals: &'a RunTotals, config: &'a PipelineConfig) -> Self {
        let velocity = &config.velocity;
        let window = 2 * velocity.half_window_frames + 1;
        // A fast particle may have its velocity from as few as five frames.
        let shortest_window =
            if velocity.min_window_travel_px > 0.0 || velocity.max_residual_ratio > 0.0 {
                window.min(5)
            } else {
                window
            };
        let windows = if shortest_window < window {
            let turns = "turns faster than a wider window follows";
            let narrower = if velocity.min_window_travel_px > 0.0 {
                format!(
                    "a particle travels {} px within it, or {turns}",
                    velocity.min_window_travel_px
                )
            } else {
                format!("a particle {turns}")
            };
            format!("{shortest_window} to {window} frames (narrower where {narrower})")
        } else {
            format!("{window} frames")
        };
        Self {
            totals,
            config,
            figures: totals.figures(),
            search: search_words(totals),
            windows,
            window,
            shortest_window,
        }
    }

    /// What the run settled on.
    fn settled(&self) -> String {
        let (config, counts) = (self.config, &self.totals.counts);
        let frames = self.totals.frames;
        let first_steps =
            if config.link.predict_new_from_neighbours && config.link.max_displacement_px > 0.0 {
                format!(
                    " (a new track's first step learnt from the images, up to {} px)",
                    config.link.max_displacement_px
                )
            } else {
                String::new()
            };
        let rejoins = if config.tracks.rejoin_frames > 0 {
            format!(
                "; broken 3D tracks rejoined across up to {} missing frames ({:.1} per frame)",
                config.tracks.rejoin_frames,
                ratio(counts.rejoined, frames)
            )
        } else {
            String::new()
        };
        let track_first = if config.tracks.track_first {
            format!(
                "; tracks first: {:.1} predicted per frame, {:.0} % of them found in both images",
                ratio(counts.predicted, frames),
                100.0 * ratio(counts.found, counts.predicted)
            )
        } else {
            String::new()
        };
        let noisy = if counts.noisy_images > 0 {
            format!(
                " (raised for sensor noise in {:.0} % of images)",
                100.0 * ratio(counts.noisy_images, 2 * frames)
            )
        } else {
            String::new()
        };
        let background = if config.detect.background_rise_per_frame > 0.0 {
            format!(
                " after a background that learns what stands still (rising {} grey levels per \
                 frame)",
                config.detect.background_rise_per_frame
            )
        } else {
            String::new()
        };
        format!(
            "stereo search {}; linking box +-{} px{first_steps}{rejoins}{track_first}; velocity \
             window {}{}; threshold {} grey levels above the local mean{noisy}{background}",
            self.search,
            config.link.box_half_side_px,
            self.windows,
            self.fits(),
            -config.detect.contrast_c
        )
    }

    /// Which fits the velocity components got.
    fn fits(&self) -> String {
        let velocity = &self.config.velocity;
        let c = &self.totals.counts;
        let components = 3 * c.vectors;
        if !velocity.adaptive_fit || components == 0 {
            return String::new();
        }
        let line = if velocity.line_past_frames > velocity.half_window_frames {
            format!(
                ", {:.0} % a line from {} frames back",
                100.0 * ratio(c.fit_components_line, components),
                velocity.line_past_frames
            )
        } else {
            String::new()
        };
        format!(
            ", fit per component: {:.0} % quadratic on the full window, {:.0} % on a \
             narrower one, {:.0} % cubic{line}",
            100.0
                * ratio(
                    components
                        - c.fit_components_narrower
                        - c.fit_components_cubic
                        - c.fit_components_line,
                    components
                ),
            100.0 * ratio(c.fit_components_narrower, components),
            100.0 * ratio(c.fit_components_cubic, components)
        )
    }

    /// The health figures in words.
    fn summary(&self) -> String {
        let f = &self.figures;
        format!(
            "{:.1} detections/image, {:.0} % linked to an earlier frame, \
             {:.2} stereo candidates per matchable particle, {:.0} % of \
             left detections matched, {:.0} % of matched particles given a velocity, {:.1} \
             fixtures/image (static spots left out)",
            f.detections_per_image,
            100.0 * f.linked_fraction,
            f.stereo_candidates_per_particle,
            100.0 * f.matched_fraction,
            100.0 * f.velocity_fraction,
            ratio(self.totals.counts.fixtures, 2 * self.totals.frames)
        )
    }

    /// What the figures say cannot be trusted.
    fn warnings(&self) -> Vec<String> {
        if self.totals.counts.vectors == 0 {
            return vec![self.why_no_vectors()];
        }
        let f = &self.figures;
        let box_px = self.config.link.box_half_side_px;
        let mut warnings = Vec::new();
        if f.linked_fraction < 0.5 {
            warnings.push(format!(
                "only {:.0} % of detections linked to an earlier frame: particles may move \
                 more than the linking box (+-{box_px} px) per frame; vectors will be few",
                100.0 * f.linked_fraction
            ));
        }
        // Only frames at least M from either end can carry a centred velocity.
        let frames = self.totals.frames;
        let centred_frames = frames.saturating_sub(self.window - 1);
        let possible = ratio(centred_frames, frames);
        if f.velocity_fraction < 0.2 * possible && f.linked_fraction >= 0.5 {
            warnings.push(format!(
                "only {:.1} % of the particles matched in both cameras were given a velocity: \
                 tracks break before the {} a centred velocity needs; particles \
                 may move more than the linking box (+-{box_px} px) per frame",
                100.0 * f.velocity_fraction,
                self.windows
            ));
        }
        let candidates_per_particle = f.stereo_candidates_per_particle;
        if candidates_per_particle > 2.5 {
            warnings.push(format!(
                "a matchable particle had {candidates_per_particle:.1} stereo candidates on \
                 average: matches are ambiguous and ghosts likely; narrow --depth-range or \
                 check the calibration"
            ));
        }
        if f.matched_fraction < 0.3 {
            warnings.push(format!(
                "only {:.0} % of left detections found a partner in the right image: check \
                 rig.json and the stereo search ({})",
                100.0 * f.matched_fraction,
                self.search
            ));
        }
        warnings
    }

    /// Why a run gave no vectors, from the first stage that came up empty.
    fn why_no_vectors(&self) -> String {
        let (totals, config) = (self.totals, self.config);
        let counts = &totals.counts;
        let detections = counts.detections_left + counts.detections_right;
        let box_px = config.link.box_half_side_px;
        if totals.frames == 0 {
            "no vectors: the recording has no frames".to_string()
        } else if detections == 0 {
            format!(
                "no vectors: no particle was detected in any image (a particle must be {} grey \
                 levels brighter than its 15 px neighbourhood, detect.contrast_c, and its \
                 area within detect.min_area_px..max_area_px)",
                -config.detect.contrast_c
            )
        } else if counts.matches == 0 {
            format!(
                "no vectors: particles were detected ({:.1} per image) but \
                 none matched between the cameras, so none lay in the stereo search: {}; \
                 check rig.json, or give the measurement volume with --depth-range",
                self.figures.detections_per_image, self.search
            )
        } else if totals.frames < self.shortest_window {
            format!(
                "no vectors: the recording has {} frames, and a centred velocity needs a \
                 particle seen through {} (velocity.half_window_frames = {})",
                totals.frames, self.shortest_window, config.velocity.half_window_frames
            )
        } else {
            format!(
                "no vectors: {} particles were matched between the cameras, but none was \
                 followed through the {} a centred velocity needs ({:.0} % of \
                 detections linked to an earlier frame): particles may move more than the \
                 linking box (+-{box_px} px) per frame",
                counts.matches,
                self.windows,
                100.0 * self.figures.linked_fraction
            )
        }
    }
}

/// The stereo search a run settled on, and where it was narrowed to the tracks.
fn search_words(totals: &RunTotals) -> String {
    let mut search = totals
        .stereo_search
        .map_or_else(|| "not set up".to_string(), |s| s.to_string());
    if let Some(learnt) = totals.learnt_search {
        search += &format!(
            ", narrowed to where the tracks are in {:.0} % of frames (last: depths \
             {:.3}..{:.3} m, disparity {:.1}..{:.1} px)",
            100.0 * ratio(totals.counts.learnt_search, totals.frames),
            learnt.near_m,
            learnt.far_m,
            learnt.min_disparity_px,
            learnt.max_disparity_px
        );
    }
    search
}

fn ratio(a: usize, b: usize) -> f64 {
    if b == 0 {
        0.0
    } else {
        a as f64 / b as f64
    }
}

/// A run's settled parameters and health figures in words, and its warnings.
#[derive(Debug, Clone, PartialEq)]
pub struct RunHealth {
    /// What the run settled on (stereo search, linking box, windows, fits, threshold).
    pub settled: String,
    /// Its health figures in words.
    pub summary: String,
    /// What its figures say cannot be trusted.
    pub warnings: Vec<String>,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn healthy() -> RunTotals {
        RunTotals {
            frames: 100,
            counts: FrameStats {
                detections_left: 3000,
                detections_right: 3000,
                matches: 2900,
                vectors: 2200,
                linked_left: 2900,
                linked_right: 2900,
                stereo_candidates: 3500,
                left_with_candidates: 2950,
                ..Default::default()
            },
            ..Default::default()
        }
    }

    /// `totals` with its counts changed by `change`.
    fn with(totals: RunTotals, change: impl FnOnce(&mut FrameStats)) -> RunTotals {
        let mut t = totals;
        change(&mut t.counts);
        t
    }

    #[test]
    fn a_healthy_run_has_no_warnings() {
        let health = healthy().health(&PipelineConfig::default());
        assert!(health.warnings.is_empty(), "{:?}", health.warnings);
        assert!(
            health.summary.contains("30.0 detections/image")
                && health.summary.contains("97 % linked"),
            "{}",
            health.summary
        );
    }

    #[test]
    fn every_run_without_vectors_says_why() {
        let config = PipelineConfig::default();
        let why = |totals: RunTotals| {
            let warnings = totals.health(&config).warnings;
            assert_eq!(warnings.len(), 1, "{warnings:?}");
            warnings[0].clone()
        };
        let none = |t: RunTotals| with(t, |c| c.vectors = 0);
        assert!(why(none(RunTotals::default())).contains("no frames"));
        let dark = RunTotals {
            frames: 50,
            ..Default::default()
        };
        assert!(why(dark).contains("no particle was detected"));
        let unmatched = with(none(healthy()), |c| c.matches = 0);
        assert!(why(unmatched).contains("none matched between the cameras"));
        let short = RunTotals {
            frames: 4,
            ..none(healthy())
        };
        assert!(why(short).contains("has 4 frames"));
        let broken = with(none(healthy()), |c| {
            c.linked_left = 300;
            c.linked_right = 300;
        });
        assert!(why(broken).contains("linking box"));
    }

    #[test]
    fn tracks_that_break_and_ambiguous_matches_are_warned_of() {
        let config = PipelineConfig::default();
        let fast = with(healthy(), |c| c.vectors = 20);
        let warnings = fast.health(&config).warnings;
        assert!(
            warnings.iter().any(|w| w.contains("tracks break")),
            "{warnings:?}"
        );
        let crowded = with(healthy(), |c| c.stereo_candidates = 9000);
        let warnings = crowded.health(&config).warnings;
        assert!(
            warnings.iter().any(|w| w.contains("ambiguous")),
            "{warnings:?}"
        );
    }
}
