//! Per-vector uncertainties against synthetic truth, and the mean-flow field binned from the
//! vectors, on the default config.

use mrptv::offline::{InMemoryRun, SyntheticRun};
use mrptv_engine::eval::{Coverage, Xyz};
use mrptv_engine::field::{default_cell_m, FieldGrid, FieldSample};
use mrptv_engine::synth::{Scenario, ScenarioSpec};
use mrptv_engine::PipelineConfig;

fn run(scenario: Scenario, seed: u64) -> (ScenarioSpec, InMemoryRun) {
    let spec = ScenarioSpec::new(scenario);
    let mut run = SyntheticRun::new(spec.clone(), PipelineConfig::default());
    run.seed = seed;
    (spec, run.run(|_| {}).expect("scenario runs"))
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

/// Positions state their errors too: on the four scenes 88-95 % of them lie within 2
/// sigma per component (docs/accuracy.md); bounded below with a margin, so a regression shows.
fn assert_positions_covered(name: &str, c: &Coverage) {
    let p = &c.position_within_2_sigma;
    for (component, fraction) in [("x", p.x), ("y", p.y), ("z", p.z)] {
        assert!(
            (0.85..=0.99).contains(&fraction),
            "{name}: {component} position within 2 sigma {fraction:.3}"
        );
    }
}

#[test]
fn velocity_uncertainties_are_calibrated_on_the_uniform_flow() {
    let (_, r) = run(Scenario::Uniform, 1);
    let c = coverage("uniform", &r);
    assert_calibrated("uniform", &c);
    assert_positions_covered("uniform", &c);
}

#[test]
fn velocity_uncertainties_are_calibrated_with_a_moving_head() {
    let (_, r) = run(Scenario::MovingHead, 1);
    let c = coverage("moving-head", &r);
    assert_calibrated("moving-head", &c);
    assert_positions_covered("moving-head", &c);
}

#[test]
fn velocity_uncertainties_are_calibrated_on_raw_hololens_geometry() {
    let (_, r) = run(Scenario::HololensRaw, 1);
    let c = coverage("hololens-raw", &r);
    assert_calibrated("hololens-raw", &c);
    assert_positions_covered("hololens-raw", &c);
}

/// A causal vector's sigmas are its own estimate's (protocol/README.md, "Uncertainties"): scored
/// against the truth at its frame they cover its errors a little less well than the refined
/// vectors' cover theirs (86-91 % within 2 sigma on these scenes); bounded so a regression shows.
#[test]
fn causal_uncertainties_cover_the_causal_vectors_errors() {
    for scenario in [Scenario::Uniform, Scenario::MovingHead] {
        let (_, r) = run(scenario, 1);
        let options = mrptv_engine::eval::EvalOptions::default();
        let report =
            mrptv_engine::eval::evaluate(&r.truth, &r.causal_tracks, &options).expect("scored");
        let name = format!("{scenario:?} causal");
        let c = report.uncertainty.expect("causal rows carry uncertainties");
        println!(
            "{name}: {} vectors; velocity within 2 sigma {:.1} {:.1} {:.1} %",
            c.rows,
            100.0 * c.velocity_within_2_sigma.x,
            100.0 * c.velocity_within_2_sigma.y,
            100.0 * c.velocity_within_2_sigma.z
        );
        assert!(c.rows > 500, "{name}: {} rows", c.rows);
        let v = &c.velocity_within_2_sigma;
        for (component, fraction) in [("u", v.x), ("v", v.y), ("w", v.z)] {
            assert!(
                (0.80..=0.98).contains(&fraction),
                "{name}: {component} within 2 sigma {fraction:.3}"
            );
        }
    }
}

/// Turbulence changes a particle's acceleration within a window: the chosen fits keep biases
/// from the path's cubic and higher terms, which the stated sigmas count (the cubic term weighed
/// against the scene's spread of it, the residual energy beyond the scene's noise as the
/// higher terms). Without them 79-83 % of the vectors lay within 2 sigma.
#[test]
fn velocity_uncertainties_are_calibrated_in_turbulence() {
    let (_, r) = run(Scenario::Turbulence, 1);
    let c = coverage("turbulence", &r);
    assert_calibrated("turbulence", &c);
    assert_positions_covered("turbulence", &c);
}

/// Scenes the uncertainty model was not tuned on hold the band too: a lab flume with sensor
/// noise, a cluttered room, a toed-in lab rig, particles crossing the image in 6-10 frames, and
/// a densely seeded tank, still and in turbulence. (Outside it, and stated in docs/accuracy.md: the
/// wind tunnel's u and v at 88 %, the long-lens rig's v and w at 87-88 %, the vortex's axial w
/// at 98.5 %.)
#[test]
fn velocity_uncertainties_are_calibrated_on_scenes_they_were_not_tuned_on() {
    for scenario in [
        Scenario::Flume,
        Scenario::Cluttered,
        Scenario::Convergent,
        Scenario::Fast,
        Scenario::Seeded,
        Scenario::SeededTurbulence,
    ] {
        let (spec, r) = run(scenario, 1);
        let name = spec.scenario.name();
        assert_calibrated(name, &coverage(name, &r));
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
