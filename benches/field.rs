//! What the live mean-flow field costs a session per frame, side by side in one run: `pipeline`,
//! the whole pipeline per frame; `field`, the field's work per frame as a session does it (the
//! frame's refined vectors binned; once a second at 30 frames a second, every cell summarised and
//! encoded as a `field` message), on the refined vectors of 300 frames of the same scene. The
//! field's share of a session's frame is `field / pipeline`. The `seeded` scene at 640x480 (the HoloLens 2 front cameras' size)
//! with 200 and 1000 particles in view.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use mrptv::protocol::{Convention, FieldMessage, ServerMessage};
use mrptv_engine::field::{CellSummary, StreamField};
use mrptv_engine::synth::{Scenario, ScenarioSpec, Synthesizer};
use mrptv_engine::{ImageView, Pipeline, PipelineConfig, StereoFrame, VelocityVector};

const FRAMES: usize = 32;
/// Frames between two `field` messages: one a second at 30 Hz.
const FRAMES_PER_MESSAGE: u64 = 30;

fn benches(c: &mut Criterion) {
    for particles in [200, 1000] {
        let spec = ScenarioSpec::new(Scenario::Seeded);
        let mut synth = Synthesizer::new(spec.clone(), particles, 7);
        let images: Vec<(Vec<u8>, Vec<u8>)> = (0..FRAMES)
            .map(|_| {
                let f = synth.next_frame();
                (f.left, f.right)
            })
            .collect();
        let (w, h) = (spec.rig.width as usize, spec.rig.height as usize);
        let frame = |index: u64| {
            let (left, right) = &images[index as usize % FRAMES];
            StereoFrame {
                index,
                t_s: index as f64 / 30.0,
                world_from_rig: None,
                left: ImageView::new(w, h, left).expect("rig-sized"),
                right: ImageView::new(w, h, right).expect("rig-sized"),
            }
        };
        // The refined vectors of 300 frames (10 s), for the field's work on its own.
        let mut pipeline =
            Pipeline::new(spec.rig.clone(), PipelineConfig::default()).expect("valid");
        let vectors: Vec<Vec<VelocityVector>> = (1..=300)
            .map(|i| pipeline.push(&frame(i)).expect("valid frame").vectors)
            .collect();
        let mut group = c.benchmark_group(format!("session_frame_{particles}"));
        group.throughput(Throughput::Elements(1));
        group.sample_size(20);
        group.bench_function("pipeline", |b| {
            let mut pipeline =
                Pipeline::new(spec.rig.clone(), PipelineConfig::default()).expect("valid");
            let mut index = 0u64;
            b.iter(|| {
                index += 1;
                pipeline
                    .push(&frame(index))
                    .expect("valid frame")
                    .vectors
                    .len()
            })
        });
        group.bench_function("field", |b| {
            let mut field = StreamField::default();
            let mut index = 0u64;
            b.iter(|| {
                index += 1;
                field.add_vectors(&vectors[index as usize % vectors.len()]);
                if !index.is_multiple_of(FRAMES_PER_MESSAGE) {
                    return 0;
                }
                let Some(grid) = field.grid() else {
                    return 0;
                };
                let cells: Vec<CellSummary> = grid.cells().collect();
                ServerMessage::Field(Box::new(FieldMessage::new(
                    "s1".into(),
                    (index, index as f64 / 30.0),
                    grid,
                    &cells,
                    false,
                    Convention::WebXr,
                )))
                .to_json()
                .len()
            })
        });
        group.finish();
    }
}

criterion_group! {
    name = field;
    config = Criterion::default().measurement_time(std::time::Duration::from_secs(5));
    targets = benches
}
criterion_main!(field);
