//! Association cost of one WILDTRACK-sized frame (7 cameras × 35 boxes, 768-, 384- and 64-dim
//! embeddings): the 21 pairwise matchings, the identity step, the whole `associate_frame`, and
//! the service's path (`frame_identities`).
use std::hint::black_box;
use std::sync::Arc;

use criterion::measurement::{Measurement, ValueFormatter, WallTime};
use criterion::{BatchSize, Criterion, Throughput, criterion_group, criterion_main};
use crossview_core::association::{
    AssociationConfig, Mode, ViewPair, associate_frame, associate_frame_with, frame_identities,
    frame_identities_with,
};
use crossview_core::calibration::Calibration;
use crossview_core::distances::{
    all_pairs_distances, euclidean_distances_with_norms, row_sq_norms,
};
use crossview_core::identity::{IdentityConfig, IdentityMethod, build_identities};
use crossview_core::matching::{hungarian, match_from_distances};
use crossview_core::memory::{Memory, MemoryConfig};
use crossview_core::tracking::{Tracker, TrackerConfig};
use crossview_core::{Detection, Frame, FrameEmbeddings};
use ndarray::Array2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

const CAMERAS: usize = 7;
const BOXES: usize = 35;

/// Embeddings of 35 persons seen by every camera: a per-person vector plus per-view noise,
/// rows shuffled per camera (so the matcher has real work to do).
fn frame_embeddings(dim: usize) -> (Frame, Vec<Option<Array2<f32>>>) {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let persons = Array2::from_shape_fn((BOXES, dim), |_| rng.sample::<f32, _>(StandardNormal));
    let mut frame = Frame::new(0, CAMERAS);
    let mut embs = Vec::new();
    for c in 0..CAMERAS {
        let mut order: Vec<usize> = (0..BOXES).collect();
        for i in (1..BOXES).rev() {
            order.swap(i, rng.random_range(0..=i));
        }
        let e = Array2::from_shape_fn((BOXES, dim), |(i, k)| {
            persons[(order[i], k)] + 0.7 * rng.sample::<f32, _>(StandardNormal)
        });
        embs.push(Some(e));
        frame.views[c] = Some(
            (0..BOXES)
                .map(|i| Detection::new([i as f32, 0.0, i as f32 + 10.0, 30.0]))
                .collect(),
        );
    }
    (frame, embs)
}

/// Row ranges of the views of a frame's embeddings.
fn ranges(embs: &FrameEmbeddings) -> Vec<std::ops::Range<usize>> {
    (0..embs.num_views()).filter_map(|c| embs.rows(c)).collect()
}

/// The production path of `associate_frame`'s pairwise step: all-pairs distances, then
/// normalisation + Hungarian + threshold per pair.
fn pairwise(embs: &FrameEmbeddings, cfg: &AssociationConfig) -> Vec<ViewPair> {
    let rows = ranges(embs);
    let mut dists = all_pairs_distances(embs.matrix(), &rows).into_iter();
    let mut pairs = Vec::with_capacity(21);
    for a in 0..rows.len() {
        for b in a + 1..rows.len() {
            let dg = dists.next().unwrap();
            pairs.push(ViewPair {
                cam_a: a,
                cam_b: b,
                matching: match_from_distances(dg, None, cfg.alpha, cfg.threshold),
            });
        }
    }
    pairs
}

/// On-CPU time of the calling thread (`CLOCK_THREAD_CPUTIME_ID`, nanosecond resolution):
/// time spent preempted by other processes does not count, which keeps numbers usable on a
/// machine shared with other builds (cache interference still counts).
struct OnCpu;

fn on_cpu_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec; the call only writes it.
    #[allow(unsafe_code)]
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    assert_eq!(rc, 0, "clock_gettime(CLOCK_THREAD_CPUTIME_ID) failed");
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

struct NsFormatter;

impl ValueFormatter for NsFormatter {
    fn scale_values(&self, ns: f64, values: &mut [f64]) -> &'static str {
        let (factor, unit) = if ns < 1e3 {
            (1.0, "ns")
        } else if ns < 1e6 {
            (1e-3, "µs")
        } else {
            (1e-6, "ms")
        };
        values.iter_mut().for_each(|v| *v *= factor);
        unit
    }
    fn scale_throughputs(&self, _: f64, _: &Throughput, _: &mut [f64]) -> &'static str {
        "ns"
    }
    fn scale_for_machines(&self, _: &mut [f64]) -> &'static str {
        "ns"
    }
}

impl Measurement for OnCpu {
    type Intermediate = u64;
    type Value = u64;
    fn start(&self) -> u64 {
        on_cpu_ns()
    }
    fn end(&self, start: u64) -> u64 {
        on_cpu_ns().saturating_sub(start)
    }
    fn add(&self, a: &u64, b: &u64) -> u64 {
        a + b
    }
    fn zero(&self) -> u64 {
        0
    }
    fn to_f64(&self, v: &u64) -> f64 {
        *v as f64
    }
    fn formatter(&self) -> &dyn ValueFormatter {
        &NsFormatter
    }
}

/// A 32-knot table falling from 1 to 0 over twice the frame's largest assigned distance: the
/// shape and size of a fitted calibration (what the identities' cost depends on).
fn calibration(pairs: &[ViewPair]) -> Calibration {
    let far = pairs
        .iter()
        .flat_map(|p| &p.matching.assignment)
        .map(|a| a.distance)
        .fold(0f32, f32::max)
        * 2.0
        + 1e-3;
    let knots = 32;
    Calibration {
        distances: (0..knots)
            .map(|k| far * k as f32 / (knots - 1) as f32)
            .collect(),
        probabilities: (0..knots)
            .map(|k| 1.0 - k as f32 / (knots - 1) as f32)
            .collect(),
        false_share: 0.5,
        samples: [1000, 1000],
    }
}

fn bench_wall(c: &mut Criterion<WallTime>) {
    bench(c, "wildtrack_frame_7x35x768", 768);
    // The default WILDTRACK model's width (six members of 64).
    bench(c, "wildtrack_frame_7x35x384", 384);
    bench(c, "wildtrack_frame_7x35x64", 64);
}

fn bench_on_cpu(c: &mut Criterion<OnCpu>) {
    bench(c, "wildtrack_frame_7x35x768_oncpu", 768);
    bench(c, "wildtrack_frame_7x35x64_oncpu", 64);
}

fn bench<M: Measurement>(c: &mut Criterion<M>, group: &str, dim: usize) {
    let (frame, per_view) = frame_embeddings(dim);
    let embs = FrameEmbeddings::from_views(&per_view).unwrap();
    let cfg = AssociationConfig::default();
    let sizes = vec![BOXES; CAMERAS];
    let pairs = pairwise(&embs, &cfg);
    let mut g = c.benchmark_group(group);
    g.bench_function("pairwise_21_matchings", |b| {
        b.iter(|| black_box(pairwise(black_box(&embs), &cfg)))
    });
    let views: Vec<&Array2<f32>> = per_view.iter().flatten().collect();
    let norms: Vec<_> = views.iter().map(|e| row_sq_norms(e.view())).collect();
    g.bench_function("distances_21_only", |b| {
        b.iter(|| {
            for a in 0..CAMERAS {
                for c in a + 1..CAMERAS {
                    black_box(euclidean_distances_with_norms(
                        views[a].view(),
                        views[c].view(),
                        norms[a].view(),
                        norms[c].view(),
                    ));
                }
            }
        })
    });
    let rows = ranges(&embs);
    g.bench_function("distances_all_pairs_blocks", |b| {
        b.iter(|| black_box(all_pairs_distances(black_box(embs.matrix()), &rows)))
    });
    let costs: Vec<Array2<f32>> = pairs
        .iter()
        .map(|p| p.matching.scores.mapv(|v| 1.0 - v))
        .collect();
    g.bench_function("hungarian_21_only", |b| {
        b.iter(|| {
            for c in &costs {
                black_box(hungarian(c.view()));
            }
        })
    });
    // Worst case for the solver's row reduction: uniform random costs (no clear best match).
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let random: Vec<Array2<f32>> = (0..pairs.len())
        .map(|_| Array2::from_shape_fn((BOXES, BOXES), |_| rng.random::<f32>()))
        .collect();
    g.bench_function("hungarian_21_random_costs", |b| {
        b.iter(|| {
            for c in &random {
                black_box(hungarian(c.view()));
            }
        })
    });
    // The solver it replaced, as a baseline: `pathfinding::kuhn_munkres` on costs scaled to
    // integers (2^30 over [0, 1], as the matcher used to).
    let kuhn_munkres = |costs: &[Array2<f32>]| {
        for c in costs {
            let (n, m) = c.dim();
            let scaled = c.iter().map(|&v| -(v as f64 * (1u64 << 30) as f64) as i64);
            let w = pathfinding::matrix::Matrix::from_vec(n, m, scaled.collect()).unwrap();
            black_box(pathfinding::kuhn_munkres::kuhn_munkres(&w));
        }
    };
    g.bench_function("hungarian_21_kuhn_munkres_baseline", |b| {
        b.iter(|| kuhn_munkres(&costs))
    });
    g.bench_function("hungarian_21_random_costs_kuhn_munkres_baseline", |b| {
        b.iter(|| kuhn_munkres(&random))
    });
    g.bench_function("identities", |b| {
        b.iter(|| black_box(build_identities(&sizes, black_box(&pairs), &cfg.identity)))
    });
    // What a served model does: the identities read the calibrated P of the entries.
    let calibrated = AssociationConfig {
        identity: IdentityConfig::new(Some(Arc::new(calibration(&pairs))), 0.2),
        ..cfg.clone()
    };
    let baseline = IdentityConfig::with_method(None, 0.4, IdentityMethod::UnionFind);
    g.bench_function("identities_union_find", |b| {
        b.iter(|| black_box(build_identities(&sizes, black_box(&pairs), &baseline)))
    });
    g.bench_function("identities_calibrated", |b| {
        b.iter(|| {
            black_box(build_identities(
                &sizes,
                black_box(&pairs),
                &calibrated.identity,
            ))
        })
    });
    for (mode, cfg, name) in [
        (Mode::Pairwise, &cfg, "pairwise"),
        (Mode::Identities, &cfg, "identities"),
        (Mode::Identities, &calibrated, "identities_calibrated"),
    ] {
        let cfg = AssociationConfig {
            mode,
            ..cfg.clone()
        };
        // A fresh copy of the embeddings right before each call: in cache, as the encoder's
        // output is in the server (a batch of copies made up front would be measured cold).
        g.bench_function(format!("associate_frame_{name}"), |b| {
            b.iter_batched(
                || embs.clone(),
                |e| black_box(associate_frame(&frame, e, &cfg)),
                BatchSize::PerIteration,
            )
        });
    }
    g.bench_function("frame_identities", |b| {
        b.iter(|| black_box(frame_identities(&frame, black_box(&embs), &cfg)))
    });
    g.bench_function("frame_identities_calibrated", |b| {
        b.iter(|| black_box(frame_identities(&frame, black_box(&embs), &calibrated)))
    });
    // With memory (what the server's streams run): the same frame again under the next frame
    // id, so every box continues its track and every pair's remembered distance is blended.
    let remembered = AssociationConfig {
        mode: Mode::Identities,
        ..calibrated.clone()
    };
    let mut memory = Memory::new(MemoryConfig::default());
    let mut next = frame.clone();
    g.bench_function("associate_frame_identities_calibrated_memory", |b| {
        b.iter_batched(
            || embs.clone(),
            |e| {
                next.frame_id += 1;
                black_box(associate_frame_with(
                    &next,
                    e,
                    &remembered,
                    Some(&mut memory),
                ))
            },
            BatchSize::PerIteration,
        )
    });
    g.bench_function("frame_identities_calibrated_memory", |b| {
        b.iter(|| {
            next.frame_id += 1;
            black_box(frame_identities_with(
                &next,
                black_box(&embs),
                &calibrated,
                &[],
                Some(&mut memory),
            ))
        })
    });
    // Tracking's share of a frame: one tracker update with the frame's identities against
    // the tracks of the frames before (the same frame again: everyone continues a track).
    let ids = frame_identities(&frame, &embs, &cfg);
    let mut tracker = Tracker::new(TrackerConfig::default());
    tracker.update(&frame, &ids, &embs);
    g.bench_function("tracker_update", |b| {
        b.iter(|| black_box(tracker.update(&frame, black_box(&ids), &embs)))
    });
    g.finish();
}

criterion_group!(wall, bench_wall);
criterion_group! {
    name = on_cpu;
    config = Criterion::default().with_measurement(OnCpu);
    targets = bench_on_cpu
}
criterion_main!(wall, on_cpu);
