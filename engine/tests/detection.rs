//! Sub-pixel detection accuracy on isolated synthetic particles, with and without a strong
//! illumination gradient.

use mrptv_engine::detect::{DetectConfig, Detector};
use mrptv_engine::geometry::PixelPoint;
use mrptv_engine::synth::{Scenario, ScenarioSpec, Synthesizer};
use mrptv_engine::ImageView;

/// RMS centroid error (px) over isolated particles, and the fraction of them detected.
fn centroid_error(spec: ScenarioSpec, config: &DetectConfig) -> (f64, f64, usize) {
    let rig = spec.rig.clone();
    let mut synth = Synthesizer::new(spec, 12, 5);
    let mut detector = Detector::new();
    let mut found = Vec::new();
    let (mut sum_sq, mut hits, mut isolated) = (0.0, 0usize, 0usize);
    for _ in 0..40 {
        let f = synth.next_frame();
        detector.detect(
            ImageView::new(rig.width as usize, rig.height as usize, &f.left).expect("sized"),
            config,
            &mut found,
        );
        let projected: Vec<(PixelPoint, f64)> = f
            .truth
            .iter()
            .filter_map(|t| {
                let r = t.position.coords.norm();
                rig.left
                    .project(&t.position)
                    .map(|p| (p, rig.left.fx * 0.0106 / r))
            })
            .collect();
        for (i, (p, d)) in projected.iter().enumerate() {
            let alone = projected
                .iter()
                .enumerate()
                .all(|(j, (q, e))| j == i || (q.x - p.x).hypot(q.y - p.y) > 2.0 * (d + e));
            let inside = p.x > 10.0
                && p.y > 10.0
                && p.x < rig.width as f64 - 10.0
                && p.y < rig.height as f64 - 10.0;
            if !alone || !inside {
                continue;
            }
            isolated += 1;
            if let Some(e) = found
                .iter()
                .map(|d| (d.centroid.x - p.x).hypot(d.centroid.y - p.y))
                .min_by(f64::total_cmp)
            {
                if e < 1.5 {
                    sum_sq += e * e;
                    hits += 1;
                }
            }
        }
    }
    (
        (sum_sq / hits.max(1) as f64).sqrt(),
        hits as f64 / isolated.max(1) as f64,
        isolated,
    )
}

#[test]
fn isolated_particles_have_sub_tenth_pixel_centroids() {
    let spec = ScenarioSpec::new(Scenario::Flume);
    let config = DetectConfig::default();
    let (rms, found, n) = centroid_error(spec, &config);
    println!("flume lighting: rms {rms:.4} px, found {found:.3} of {n}");
    assert!(n > 200);
    assert!(rms <= 0.1, "rms centroid error {rms:.4} px");
    assert!(found >= 0.98, "found {found:.3}");
}

#[test]
fn strong_illumination_gradient_is_handled() {
    let mut spec = ScenarioSpec::new(Scenario::Flume);
    // Background from 10 to 150 grey levels across the image; particles twice as bright on the
    // right as on the left.
    spec.background = 10.0;
    spec.background_gradient = 140.0;
    spec.illumination_gradient = 0.9;
    let config = DetectConfig::default();
    let (rms, found, n) = centroid_error(spec, &config);
    println!("gradient: rms {rms:.4} px, found {found:.3} of {n}");
    assert!(rms <= 0.1, "rms centroid error {rms:.4} px");
    assert!(found >= 0.98, "found {found:.3}");
}

/// A real camera's particle images: Gaussian spots (optics blur 1 px), smeared over half the
/// frame interval by up to 8 px per frame of motion (streaks up to a third of the particle's
/// diameter), in a vignetted image with sensor noise 4. Longer streaks (past `max_axis_ratio`)
/// are taken for overlapping particles and cut in two: a known limit.
#[test]
fn gaussian_motion_blurred_particles_keep_sub_tenth_pixel_centroids() {
    use mrptv_engine::synth::{Clutter, Flow};
    let mut spec = ScenarioSpec::new(Scenario::Flume);
    spec.flow = Flow::Uniform(nalgebra::Vector3::new(0.2, -0.08, 0.0));
    spec.noise_sd = 4.0;
    spec.clutter = Clutter {
        psf_sigma_px: 1.0,
        exposure_fraction: 0.5,
        vignetting: 0.5,
        ..Clutter::default()
    };
    let (rms, found, n) = centroid_error(spec, &DetectConfig::default());
    println!("gaussian, motion blur, vignetting: rms {rms:.4} px, found {found:.3} of {n}");
    assert!(n > 200);
    assert!(rms <= 0.1, "rms centroid error {rms:.4} px");
    assert!(found >= 0.98, "found {found:.3}");
}

/// A dark room at high gain: sensor noise of 10 grey levels. The fixed contrast C = -6 passes
/// noise as particles; the threshold measured from each image's noise does not, and still finds
/// the particles.
#[test]
fn the_threshold_follows_each_images_noise() {
    let mut spec = ScenarioSpec::new(Scenario::Flume);
    spec.noise_sd = 10.0;
    let rig = spec.rig.clone();
    let (w, h) = (rig.width as usize, rig.height as usize);
    let count = |config: &DetectConfig| {
        let mut synth = Synthesizer::new(spec.clone(), 30, 2);
        let mut detector = Detector::new();
        let (mut found, mut visible, mut c) = (Vec::new(), 0, 0.0);
        let mut detections = 0;
        for _ in 0..10 {
            let f = synth.next_frame();
            detector.detect(
                ImageView::new(w, h, &f.left).expect("sized"),
                config,
                &mut found,
            );
            detections += found.len();
            visible += f.visible_in_both;
            c = detector.last_contrast_c();
        }
        (detections as f64 / visible as f64, c)
    };
    let (adaptive, c) = count(&DetectConfig::default());
    let (fixed, _) = count(&DetectConfig {
        noise_sigmas: 0.0,
        ..DetectConfig::default()
    });
    println!("detections per visible particle: {adaptive:.2} (C = {c:.1}), fixed C: {fixed:.2}");
    assert!((0.8..=1.3).contains(&adaptive), "{adaptive}");
    assert!(fixed > 2.0, "{fixed}");
    assert!(c < -10.0, "{c}");
}
