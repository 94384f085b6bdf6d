//! Throughput of detection and of the whole per-frame pipeline, on densely seeded stereo pairs
//! (the `seeded` scene: 2.5-6 px particles filling both views) at 640x480 (the HoloLens 2 front
//! cameras' size) and 960x720 (the same view, finer pixels), with 50, 200, 1000 and 4000
//! particles in view. Per pair size and density:
//! - `detect_*`: detection of one image, one thread (the stage that grows with pixels and
//!   overlaps);
//! - `pipeline_*_1_thread`: the whole pipeline on one core (detection of both images, linking,
//!   stereo matching, 3D tracks and velocity fits), stereo pairs per second;
//! - `pipeline_*_2_threads`: the same with the two cameras' stages in parallel, as sessions and
//!   `process` run it.
//!
//! What is not detection (linking to velocities) is the 1-thread pipeline time minus twice the
//! detection time.

// criterion's macros define undocumented functions.
#![allow(missing_docs)]

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use mrptv_engine::detect::{DetectConfig, Detector};
use mrptv_engine::synth::{parallel_rig, Scenario, ScenarioSpec, Synthesizer};
use mrptv_engine::{ImageView, Pipeline, PipelineConfig, StereoFrame};

const FRAMES: usize = 32;

/// Left and right pixels of one stereo pair.
type Pair = (Vec<u8>, Vec<u8>);

/// The seeded scene at `width` x `height` (same field of view) with `particles` in view.
fn frames(width: u32, height: u32, particles: usize) -> (ScenarioSpec, Vec<Pair>) {
    let mut spec = ScenarioSpec::new(Scenario::Seeded);
    let scale = f64::from(width) / f64::from(spec.rig.width);
    spec.rig = parallel_rig(width, height, 363.0 * scale, 0.099);
    let mut synth = Synthesizer::new(spec.clone(), particles, 7);
    let frames = (0..FRAMES).map(|_| {
        let f = synth.next_frame();
        (f.left, f.right)
    });
    (spec, frames.collect())
}

fn view(w: usize, h: usize, pixels: &[u8]) -> ImageView<'_> {
    ImageView::new(w, h, pixels).expect("rig-sized")
}

fn benches(c: &mut Criterion) {
    for (width, height) in [(640, 480), (960, 720)] {
        for particles in [50, 200, 1000, 4000] {
            let (spec, images) = frames(width, height, particles);
            let (w, h) = (width as usize, height as usize);
            let size = format!("{width}x{height}");

            let mut group = c.benchmark_group(format!("detect_{size}"));
            group.throughput(Throughput::Elements(1));
            if particles >= 1000 {
                group.sample_size(10);
            }
            let mut detector = Detector::new();
            let mut out = Vec::new();
            let mut n = 0;
            group.bench_with_input(
                BenchmarkId::from_parameter(particles),
                &particles,
                |b, _| {
                    b.iter(|| {
                        n = (n + 1) % FRAMES;
                        detector.detect(
                            view(w, h, &images[n].0),
                            &DetectConfig::default(),
                            &mut out,
                        );
                        out.len()
                    })
                },
            );
            group.finish();

            for threads in [1, 2] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .expect("thread pool");
                let label = if threads == 1 { "thread" } else { "threads" };
                let mut group = c.benchmark_group(format!("pipeline_{size}_{threads}_{label}"));
                group.throughput(Throughput::Elements(1));
                if particles >= 1000 {
                    group.sample_size(10);
                }
                group.bench_with_input(
                    BenchmarkId::from_parameter(particles),
                    &particles,
                    |b, _| {
                        let mut pipeline =
                            Pipeline::new(spec.rig.clone(), PipelineConfig::default())
                                .expect("valid");
                        let mut index = 0u64;
                        b.iter(|| {
                            // Replaying the same frames in a loop: one track break per loop, as
                            // in a real stream with occasional dropouts.
                            let (left, right) = &images[index as usize % FRAMES];
                            index += 1;
                            let frame = StereoFrame {
                                index,
                                t_s: index as f64 / 30.0,
                                world_from_rig: None,
                                left: view(w, h, left),
                                right: view(w, h, right),
                            };
                            pool.install(|| pipeline.push(&frame))
                                .expect("valid frame")
                                .vectors
                                .len()
                        })
                    },
                );
                group.finish();
            }
        }
    }
}

criterion_group! {
    name = pipeline;
    config = Criterion::default().sample_size(20).measurement_time(std::time::Duration::from_secs(3));
    targets = benches
}
criterion_main!(pipeline);
