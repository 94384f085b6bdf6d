//! Per-vector uncertainties against synthetic truth, and the mean-flow field binned from the
//! vectors, on the default config.

use mrptv::eval::{Coverage, EvalOptions, Xyz};
use mrptv::offline::{run_in_memory, InMemoryRun};
use mrptv::ptv::field::{default_cell_m, FieldGrid, FieldSample};
use mrptv::ptv::PipelineConfig;
use mrptv::synth::{Scenario, ScenarioSpec};

fn run(scenario: Scenario, seed: u64) -> (ScenarioSpec, InMemoryRun) {
    let spec = ScenarioSpec::new(scenario);
    let config = PipelineConfig::default();
    let eval = EvalOptions {
        window_frames: config.velocity.half_window_frames as u64,
        ..Default::default()
    };
    let run = run_in_memory(
        spec.clone(),
        config,
        spec.default_frames,
        spec.default_particles,
        seed,
        &eval,
        |_| {},
    )
    .expect("scenario runs");
    (spec, run)
}

fn coverage(name: &str, run: &InMemoryRun) -> Coverage {
    let c = run
        .report
        .uncertainty
        .clone()
        .expect("tracks carry uncertainties");
    let row = |label: &str, v: &Xyz| {
        format!(
            "{label} {:.1} {:.1} {:.1} %",
            100.0 * v.x,
            100.0 * v.y,
            100.0 * v.z
        )
    };
    println!(
        "{name}: {} vectors; velocity {} / {}; position {} / {}; median sigma {:.5} {:.5} {:.5} m/s",
        c.rows,
        row("within 1 sigma", &c.velocity_within_1_sigma),
        row("2 sigma", &c.velocity_within_2_sigma),
        row("within 1 sigma", &c.position_within_1_sigma),
        row("2 sigma", &c.position_within_2_sigma),
        c.median_velocity_sigma_m_per_s.x,
        c.median_velocity_sigma_m_per_s.y,
        c.median_velocity_sigma_m_per_s.z,
    );
    c
}

/// The band: per velocity component, 90 % to 98 % of the vectors within 2 sigma (a
/// Gaussian error with the stated sigma gives 95.4 %; fewer means sigmas too small, more too
/// large to be useful).
fn assert_calibrated(name: &str, c: &Coverage) {
    let v = &c.velocity_within_2_sigma;
    for (component, fraction) in [("u", v.x), ("v", v.y), ("w", v.z)] {
        assert!(
            (0.90..=0.98).contains(&fraction),
            "{name}: {component} within 2 sigma {:.3}",
            fraction
        );
    }
    assert!(c.rows > 500, "{name}: only {} vectors scored", c.rows);
}

#[test]
fn velocity_uncertainties_are_calibrated_on_the_uniform_flow() {
    let (_, r) = run(Scenario::Uniform, 1);
    assert_calibrated("uniform", &coverage("uniform", &r));
}

#[test]
fn velocity_uncertainties_are_calibrated_with_a_moving_head() {
    let (_, r) = run(Scenario::MovingHead, 1);
    assert_calibrated("moving-head", &coverage("moving-head", &r));
}

#[test]
fn velocity_uncertainties_are_calibrated_on_raw_hololens_geometry() {
    let (_, r) = run(Scenario::HololensRaw, 1);
    assert_calibrated("hololens-raw", &coverage("hololens-raw", &r));
}

/// Turbulence falls short of the band: 79-83 % of the vectors lie within 2 sigma (the issue asks
/// for 90 %), 49-52 % within 1 sigma. The core of its errors is about 1.5 times what the noise
/// and the modelled biases explain; tried and not the cause: the pooled noise's weight, the
/// cubic bias (even 16 times it moved coverage by 2 points), the line fit and narrowed windows.
/// Bounded at what is reached, so a regression shows; the README states the gap.
#[test]
fn velocity_uncertainties_in_turbulence_are_short_of_the_band() {
    let (_, r) = run(Scenario::Turbulence, 1);
    let c = coverage("turbulence", &r);
    let v = &c.velocity_within_2_sigma;
    for (component, fraction) in [("u", v.x), ("v", v.y), ("w", v.z)] {
        assert!(
            (0.77..=0.98).contains(&fraction),
            "turbulence: {component} within 2 sigma {fraction:.3}"
        );
    }
}

/// The cells' mean velocities from `run`'s vectors, next to the truth field averaged over the
/// same samples (the flow's velocity where and when each vector was measured).
fn field_against_truth(
    spec: &ScenarioSpec,
    run: &InMemoryRun,
    cell_m: f64,
) -> Vec<(usize, nalgebra::Vector3<f64>, nalgebra::Vector3<f64>)> {
    let mut measured = FieldGrid::new(cell_m, None).expect("grid");
    let mut truth = FieldGrid::new(cell_m, None).expect("grid");
    for r in &run.tracks {
        let sample = FieldSample::from(r);
        measured.add(sample);
        truth.add(FieldSample {
            velocity: spec.flow.velocity(&r.position, r.t_s),
            ..sample
        });
    }
    measured
        .cells()
        .zip(truth.cells())
        .map(|(m, t)| {
            assert_eq!(m.index, t.index);
            (m.samples, m.mean, t.mean)
        })
        .collect()
}

#[test]
fn field_cells_of_a_uniform_flow_hold_its_speed_within_one_percent() {
    let (spec, r) = run(Scenario::Uniform, 1);
    let positions: Vec<_> = r.tracks.iter().map(|t| t.position).collect();
    let cell_m = default_cell_m(&positions).expect("a cell size");
    let cells = field_against_truth(&spec, &r, cell_m);
    let full: Vec<_> = cells.iter().filter(|(n, ..)| *n >= 20).collect();
    let worst = full
        .iter()
        .map(|(_, m, t)| (m - t).norm() / t.norm())
        .fold(0.0, f64::max);
    println!(
        "uniform field: cell {cell_m} m, {} cells, {} with >= 20 samples, worst mean error {:.3} % of the speed",
        cells.len(),
        full.len(),
        100.0 * worst
    );
    assert!(
        full.len() >= 50,
        "only {} cells with 20 samples",
        full.len()
    );
    assert!(worst <= 0.01, "worst cell mean error {:.4}", worst);
}

#[test]
fn field_cells_of_a_vortex_match_the_truth_over_the_same_samples() {
    let (spec, r) = run(Scenario::Vortex, 1);
    let positions: Vec<_> = r.tracks.iter().map(|t| t.position).collect();
    let cell_m = default_cell_m(&positions).expect("a cell size");
    let cells = field_against_truth(&spec, &r, cell_m);
    let full: Vec<_> = cells.iter().filter(|(n, ..)| *n >= 20).collect();
    let mean_speed = full.iter().map(|(_, _, t)| t.norm()).sum::<f64>() / full.len() as f64;
    let relative: Vec<f64> = full
        .iter()
        .map(|(_, m, t)| (m - t).norm() / t.norm().max(mean_speed * 0.1))
        .collect();
    let worst = relative.iter().copied().fold(0.0, f64::max);
    println!(
        "vortex field: cell {cell_m} m, {} cells, {} with >= 20 samples, mean cell speed {mean_speed:.3} m/s, worst mean error {:.3} % of the cell's speed",
        cells.len(),
        full.len(),
        100.0 * worst
    );
    assert!(
        full.len() >= 20,
        "only {} cells with 20 samples",
        full.len()
    );
    assert!(worst <= 0.02, "worst cell mean error {:.4}", worst);
}
