//! Throughput of detection and of the whole per-frame pipeline on 640x480 stereo pairs
//! (the HoloLens 2 front cameras' size), for 50, 200 and 1000 particles in view. One thread.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use mrptv::ptv::detect::{DetectConfig, Detector};
use mrptv::ptv::{ImageView, Pipeline, PipelineConfig, StereoFrame};
use mrptv::synth::{Scenario, ScenarioSpec, Synthesizer};

const FRAMES: usize = 32;

/// Left and right pixels of one stereo pair.
type Pair = (Vec<u8>, Vec<u8>);

fn frames(particles: usize) -> (ScenarioSpec, Vec<Pair>) {
    let spec = ScenarioSpec::new(Scenario::Flume);
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
    for particles in [50, 200, 1000] {
        let (spec, images) = frames(particles);
        let (w, h) = (spec.rig.width as usize, spec.rig.height as usize);

        let mut group = c.benchmark_group("detect_640x480");
        group.throughput(Throughput::Elements(1));
        let mut detector = Detector::new();
        let mut out = Vec::new();
        let mut n = 0;
        group.bench_with_input(
            BenchmarkId::from_parameter(particles),
            &particles,
            |b, _| {
                b.iter(|| {
                    n = (n + 1) % FRAMES;
                    detector.detect(view(w, h, &images[n].0), &DetectConfig::default(), &mut out);
                    out.len()
                })
            },
        );
        group.finish();

        let mut group = c.benchmark_group("pipeline_stereo_pair_640x480");
        group.throughput(Throughput::Elements(1));
        group.bench_with_input(
            BenchmarkId::from_parameter(particles),
            &particles,
            |b, _| {
                let mut pipeline =
                    Pipeline::new(spec.rig.clone(), PipelineConfig::default()).expect("valid");
                let mut index = 0u64;
                b.iter(|| {
                    // Replaying the same frames in a loop: one track break per loop, as in a real
                    // stream with occasional dropouts.
                    let (left, right) = &images[index as usize % FRAMES];
                    index += 1;
                    let frame = StereoFrame {
                        index,
                        t_s: index as f64 / 30.0,
                        world_from_rig: None,
                        left: view(w, h, left),
                        right: view(w, h, right),
                    };
                    pipeline.push(&frame).expect("valid frame").vectors.len()
                })
            },
        );
        group.finish();
    }
}

criterion_group! {
    name = pipeline;
    config = Criterion::default().sample_size(30).measurement_time(std::time::Duration::from_secs(3));
    targets = benches
}
criterion_main!(pipeline);
