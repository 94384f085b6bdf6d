//! Frame times from the HoloLens's sensor clock. Research mode stamps each frame twice: host
//! ticks (the QPC clock poses are located on), which reach the host with per-camera jitter of a
//! millisecond or more, and `sensor_ticks` (nanoseconds, one clock for all four visible-light
//! cameras), which step exactly with the exposures. Pairs and `t_s` come from the sensor clock;
//! a robust line fitted from sensor to host time says when on the host clock each exposure was,
//! and the pose there is interpolated between the poses the frames brought (each located at its
//! own, jittered host stamp).

use std::collections::VecDeque;

use nalgebra::Isometry3;

/// Which clock times the bridge's frames (`mrptv hl2ss --frame-clock`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum FrameClock {
    /// `sensor_ticks`: exact exposure times; poses at the fitted host time of each exposure.
    #[default]
    Sensor,
    /// The host ticks as sent, and each left frame's own pose (what a client without the sensor
    /// clock gets; kept to measure what the jitter costs).
    Host,
}

/// Sensor nanoseconds per host tick (100 ns).
const NS_PER_TICK: u64 = 100;

/// A frame's time on `clock`, host ticks (100 ns); a frame whose trailer carries no sensor
/// stamp (0) is timed by its host ticks.
pub(crate) fn frame_ticks(clock: FrameClock, host_ticks: u64, sensor_ns: u64) -> u64 {
    match clock {
        FrameClock::Sensor if sensor_ns != 0 => sensor_ns / NS_PER_TICK,
        _ => host_ticks,
    }
}

/// Frames the sensor-to-host line is fitted over: 10 s at 30 Hz, long enough to average the
/// jitter down, short enough to follow the clocks' drift.
const FIT_WINDOW: usize = 300;

/// The rate is fitted only over frames spanning this long, ticks (5 s): over less, a
/// millisecond of jitter moves the slope by more than two crystal clocks ever differ.
const MIN_RATE_SPAN_TICKS: f64 = 5e7;

/// Two crystal clocks differ in rate by far less than this (1,000 ppm); a fitted rate beyond
/// it is the jitter's, not the clocks'.
const MAX_RATE_ERROR: f64 = 1e-3;

/// A robust line `host = offset + rate * sensor` over the newest frames: the rate is the median
/// of slopes between frames half a window apart (1 until they span 5 s), the offset the median
/// residual, so stamps delayed by a busy device do not pull it.
#[derive(Debug, Default)]
pub(crate) struct SensorToHost {
    /// (sensor, host) in ticks, relative to the first frame's.
    samples: VecDeque<(f64, f64)>,
    origin: Option<(u64, u64)>,
}

impl SensorToHost {
    pub(crate) fn observe(&mut self, sensor_ticks: u64, host_ticks: u64) {
        let (s0, h0) = *self.origin.get_or_insert((sensor_ticks, host_ticks));
        self.samples.push_back((
            sensor_ticks as f64 - s0 as f64,
            host_ticks as f64 - h0 as f64,
        ));
        if self.samples.len() > FIT_WINDOW {
            self.samples.pop_front();
        }
    }

    /// The host time of `sensor_ticks`, ticks; `None` before any frame.
    pub(crate) fn host_at(&self, sensor_ticks: u64) -> Option<f64> {
        let (s0, h0) = self.origin?;
        let half = self.samples.len() / 2;
        let mut slopes: Vec<f64> = (0..half)
            .filter_map(|i| {
                let ((sa, ha), (sb, hb)) = (self.samples[i], self.samples[i + half]);
                (sb - sa >= MIN_RATE_SPAN_TICKS).then(|| (hb - ha) / (sb - sa))
            })
            .collect();
        let rate = median(&mut slopes)
            .unwrap_or(1.0)
            .clamp(1.0 - MAX_RATE_ERROR, 1.0 + MAX_RATE_ERROR);
        let mut residuals: Vec<f64> = self.samples.iter().map(|(s, h)| h - rate * s).collect();
        let offset = median(&mut residuals)?;
        Some(h0 as f64 + offset + rate * (sensor_ticks as f64 - s0 as f64))
    }
}

fn median(values: &mut [f64]) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    values.sort_by(f64::total_cmp);
    let n = values.len();
    Some(if n % 2 == 1 {
        values[n / 2]
    } else {
        (values[n / 2 - 1] + values[n / 2]) / 2.0
    })
}

/// Poses kept to interpolate in: a third of a second of both cameras' frames.
const POSE_HISTORY: usize = 20;

/// Extrapolating past the newest pose, the other pose used is at least this much older, ticks
/// (10 ms): not the other camera's pose of the same pair, whose stamp differs only by jitter.
const MIN_EXTRAPOLATION_BASE_TICKS: f64 = 100_000.0;

/// The rig node's poses as the frames brought them, each at its host stamp.
#[derive(Debug, Default)]
pub(crate) struct PoseHistory {
    /// (host ticks, world from node), in time order.
    poses: VecDeque<(f64, Isometry3<f64>)>,
}

impl PoseHistory {
    pub(crate) fn push(&mut self, host_ticks: u64, pose: Isometry3<f64>) {
        let t = host_ticks as f64;
        let at = self.poses.partition_point(|(u, _)| *u <= t);
        self.poses.insert(at, (t, pose));
        if self.poses.len() > POSE_HISTORY {
            self.poses.pop_front();
        }
    }

    /// The pose at host time `t`: between the poses either side of it, or (past the newest)
    /// on the line through the newest and an earlier frame's; `None` with fewer than two poses.
    pub(crate) fn at(&self, t: f64) -> Option<Isometry3<f64>> {
        let after = self.poses.partition_point(|(u, _)| *u <= t);
        let (a, b) = if after == 0 {
            (self.poses.front()?, self.poses.get(1)?)
        } else if after < self.poses.len() {
            (&self.poses[after - 1], &self.poses[after])
        } else {
            let newest = self.poses.back()?;
            let earlier = self
                .poses
                .iter()
                .rev()
                .find(|(u, _)| newest.0 - u >= MIN_EXTRAPOLATION_BASE_TICKS)
                .or_else(|| self.poses.iter().rev().nth(1))?;
            (earlier, newest)
        };
        if b.0 <= a.0 {
            return Some(b.1);
        }
        Some(interpolate(&a.1, &b.1, (t - a.0) / (b.0 - a.0)))
    }
}

/// `a` moved towards `b` by the fraction `f` of the way (beyond it for `f > 1`): translation on
/// the line, rotation about the one axis that takes `a` to `b`.
fn interpolate(a: &Isometry3<f64>, b: &Isometry3<f64>, f: f64) -> Isometry3<f64> {
    let translation = a.translation.vector.lerp(&b.translation.vector, f);
    let delta = b.rotation * a.rotation.inverse();
    let rotation = nalgebra::UnitQuaternion::from_scaled_axis(delta.scaled_axis() * f) * a.rotation;
    Isometry3::from_parts(translation.into(), rotation)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn the_fitted_line_ignores_jitter_and_a_late_stamp() {
        let mut fit = SensorToHost::default();
        let truth = |s: u64| 5.0e9 + 1.000_02 * s as f64;
        for i in 0..400u64 {
            let sensor = 1_000_000 + i * 330_000;
            let jitter = [-9_000.0, 4_000.0, 10_000.0, -3_000.0, 0.0][i as usize % 5];
            let late = if i % 50 == 30 { 500_000.0 } else { 0.0 };
            fit.observe(sensor, (truth(sensor) + jitter + late) as u64);
        }
        let s = 1_000_000 + 401 * 330_000;
        let error = fit.host_at(s).expect("fitted") - truth(s);
        assert!(error.abs() < 2_000.0, "{error} ticks off");
    }

    #[test]
    fn poses_are_interpolated_between_and_extrapolated_past_their_stamps() {
        let pose = |t: f64| {
            Isometry3::from_parts(
                Translation3::new(0.1 * t, 0.0, 1.0),
                UnitQuaternion::from_euler_angles(0.0, 0.2 * t, 0.0),
            )
        };
        let mut history = PoseHistory::default();
        for t in [0.0, 0.033, 0.0335, 0.066] {
            history.push((t * 1e7) as u64, pose(t));
        }
        for t in [0.02, 0.05, 0.07] {
            let got = history.at(t * 1e7).expect("enough poses");
            let want = pose(t);
            assert!((got.translation.vector - want.translation.vector).norm() < 1e-9);
            assert!(got.rotation.angle_to(&want.rotation) < 1e-9, "at {t}");
        }
        assert!(PoseHistory::default().at(0.0).is_none());
    }

    #[test]
    fn frames_without_a_sensor_stamp_keep_their_host_ticks() {
        assert_eq!(frame_ticks(FrameClock::Sensor, 7, 3_300), 33);
        assert_eq!(frame_ticks(FrameClock::Sensor, 7, 0), 7);
        assert_eq!(frame_ticks(FrameClock::Host, 7, 3_300), 7);
    }
}
