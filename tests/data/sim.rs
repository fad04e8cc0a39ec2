//! Simulator integration tests: determinism, complete frames, the CLI output format and the
//! calibrated sanity check (ground truth and geometry agree).
use crossview_core::matching::hungarian;
use crossview_core::{Batch, Detection};
use crossview_data::sim::{
    AppearanceConfig, BODY_RADIUS_M, DetectorNoise, SimConfig, Simulator, ground_distances,
    simulate,
};

fn small(preset: &str, frames: u64, seed: u64) -> SimConfig {
    let mut cfg = SimConfig::preset(preset).unwrap();
    cfg.frames = frames;
    cfg.seed = seed;
    cfg
}

#[test]
fn same_seed_same_recording_other_seed_differs() {
    let mut cfg = small("square4", 40, 7);
    cfg.appearance = Some(AppearanceConfig::default());
    let a = simulate(&cfg).unwrap();
    let b = simulate(&cfg).unwrap();
    assert_eq!(a, b);
    cfg.seed = 8;
    let c = simulate(&cfg).unwrap();
    assert_ne!(a, c);
}

#[test]
fn noise_settings_do_not_change_the_people() {
    // one seed: clean ground truth and noisy detections describe the same scene
    let mut cfg = small("pair", 30, 3);
    cfg.detector = DetectorNoise::none();
    let mut clean = Simulator::new(&cfg).unwrap();
    cfg.detector = DetectorNoise::default();
    cfg.appearance = Some(AppearanceConfig::default());
    let mut noisy = Simulator::new(&cfg).unwrap();
    for _ in 0..30 {
        assert_eq!(clean.people(), noisy.people());
        clean.next_frame().unwrap();
        noisy.next_frame().unwrap();
    }
}

#[test]
fn every_frame_has_a_valid_batch_for_every_camera() {
    let mut cfg = small("wildtrack", 30, 1);
    cfg.first_frame_id = 100;
    cfg.frame_step = 5;
    cfg.appearance = Some(AppearanceConfig {
        dim: 16,
        ..AppearanceConfig::default()
    });
    let rec = simulate(&cfg).unwrap();
    assert_eq!(rec.scene.cameras.len(), 7);
    assert!(
        rec.scene
            .cameras
            .iter()
            .all(|c| c.width == 1920 && c.height == 1080)
    );
    assert_eq!(rec.frames.len(), 30);
    let (mut boxes, mut empty, mut fps) = (0, 0, 0);
    for (k, f) in rec.frames.iter().enumerate() {
        assert_eq!(f.frame_id, 100 + 5 * k as u64);
        assert!(f.is_complete());
        assert_eq!(f.views.len(), 7);
        for (c, v) in f.views.iter().enumerate() {
            let v = v.as_ref().unwrap();
            empty += v.is_empty() as usize;
            for (i, d) in v.iter().enumerate() {
                d.validate(&format!("frame {k} cam {c} det {i}"), Some(16))
                    .unwrap();
                assert!(d.bbox[2] <= 1920.0 && d.bbox[3] <= 1080.0);
                fps += d.id.is_none() as usize;
            }
            boxes += v.len();
        }
    }
    // a busy scene: ~10 people per view on average, a few false positives
    assert!(boxes > 30 * 7 * 4, "only {boxes} boxes");
    assert!(fps > 0, "no false positives with the default detector");
    let _ = empty;
}

#[test]
fn no_ids_leaves_ids_out() {
    let mut cfg = small("pair", 10, 2);
    cfg.ids = false;
    let rec = simulate(&cfg).unwrap();
    assert!(
        rec.frames
            .iter()
            .all(|f| { f.views.iter().flatten().flatten().all(|d| d.id.is_none()) })
    );
    assert!(rec.frames.iter().map(|f| f.num_boxes()).sum::<usize>() > 0);
}

#[test]
fn invalid_configs_are_rejected_with_the_field_named() {
    let mut cfg = small("pair", 10, 2);
    cfg.fps = f64::NAN;
    assert!(
        Simulator::new(&cfg)
            .unwrap_err()
            .to_string()
            .contains("fps")
    );
    let mut cfg = small("pair", 10, 2);
    cfg.detector.miss_rate = -0.1;
    assert!(
        Simulator::new(&cfg)
            .unwrap_err()
            .to_string()
            .contains("miss_rate")
    );
    let mut cfg = small("pair", 10, 2);
    cfg.frame_step = 0;
    assert!(Simulator::new(&cfg).is_err());
    assert!(SimConfig::preset("mall").is_err());
}

/// SPEC §5-style pairwise accuracy of ground-plane matching with a distance gate (metres).
fn calibrated_accuracy(cfg: &SimConfig, gate: f32) -> (f64, usize) {
    let sim = Simulator::new(cfg).unwrap();
    let cams = sim.cameras().to_vec();
    let (mut good, mut total) = (0usize, 0usize);
    for frame in sim {
        // boxes cut at the image border do not show where the feet are: leave them out
        let views: Vec<Vec<Detection>> = frame
            .views
            .iter()
            .zip(&cams)
            .map(|(v, cam)| {
                let (w, h) = (cam.spec.width as f32, cam.spec.height as f32);
                v.as_ref()
                    .unwrap()
                    .iter()
                    .filter(|d| d.bbox[0] > 0.5 && d.bbox[2] < w - 0.5 && d.bbox[3] < h - 0.5)
                    .cloned()
                    .collect()
            })
            .collect();
        for i in 0..views.len() {
            for j in i + 1..views.len() {
                let (a, b) = (&views[i], &views[j]);
                if a.is_empty() || b.is_empty() {
                    continue;
                }
                let d = ground_distances(&cams[i], a, &cams[j], b, BODY_RADIUS_M);
                // gate before assigning, so far-apart leftovers cannot trade partners
                let kept: Vec<(usize, usize)> = hungarian(d.mapv(|v| v.min(gate)).view())
                    .into_iter()
                    .filter(|&(x, y)| d[[x, y]] < gate)
                    .collect();
                let ids_b: Vec<u64> = b.iter().map(|d| d.id.unwrap()).collect();
                let ids_a: Vec<u64> = a.iter().map(|d| d.id.unwrap()).collect();
                let mut union: Vec<u64> = ids_a.iter().chain(&ids_b).copied().collect();
                union.sort_unstable();
                union.dedup();
                let correct = kept.iter().filter(|&&(x, y)| ids_a[x] == ids_b[y]).count();
                let tn_a = (0..a.len())
                    .filter(|x| !kept.iter().any(|k| k.0 == *x) && !ids_b.contains(&ids_a[*x]))
                    .count();
                let tn_b = (0..b.len())
                    .filter(|y| !kept.iter().any(|k| k.1 == *y) && !ids_a.contains(&ids_b[*y]))
                    .count();
                good += correct + tn_a + tn_b;
                total += union.len();
            }
        }
    }
    (good as f64 / total as f64, total)
}

#[test]
fn calibrated_ground_plane_matching_is_nearly_perfect_without_detector_noise() {
    for preset in ["square4", "wildtrack"] {
        let mut cfg = small(preset, 25, 11);
        cfg.detector = DetectorNoise::none();
        // full boxes: the bottom-centre of a box is the person's feet
        cfg.render.shrink_occluded = false;
        let (acc, n) = calibrated_accuracy(&cfg, 0.4);
        assert!(n > 500, "{preset}: too few identities compared ({n})");
        assert!(
            acc > 0.99,
            "{preset}: calibrated accuracy {acc:.4} over {n}"
        );
    }
}

#[test]
fn detector_noise_makes_the_calibrated_baseline_imperfect() {
    // the realism knobs bite: a model that works on noisy data is not fooled by it
    let mut cfg = small("square4", 25, 11);
    cfg.detector = DetectorNoise {
        jitter: 0.08,
        ..DetectorNoise::default()
    };
    cfg.ids = true;
    let sim = Simulator::new(&cfg).unwrap();
    let cams = sim.cameras().to_vec();
    let mut far = 0usize;
    let mut pairs = 0usize;
    for frame in sim {
        let a = frame.views[0].as_ref().unwrap();
        let b = frame.views[1].as_ref().unwrap();
        let d = ground_distances(&cams[0], a, &cams[1], b, BODY_RADIUS_M);
        for (x, da) in a.iter().enumerate() {
            for (y, db) in b.iter().enumerate() {
                if da.id.is_some() && da.id == db.id {
                    pairs += 1;
                    far += (d[[x, y]] > 0.3) as usize;
                }
            }
        }
    }
    assert!(pairs > 50);
    assert!(
        far > 0,
        "noisy boxes should sometimes land far from the truth"
    );
}

#[test]
fn cli_writes_a_spec_recording_byte_identically() {
    let dir = tempfile::tempdir().unwrap();
    let run = |name: &str, extra: &[&str]| {
        let out = dir.path().join(name);
        let mut args = vec![
            "crossview",
            "simulate",
            "--preset",
            "pair",
            "--frames",
            "20",
            "--seed",
            "5",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let cli = <crossview::cli::Cli as clap::Parser>::try_parse_from(args).unwrap();
        match cli.command {
            crossview::cli::Command::Simulate(a) => crossview::cli::simulate::run(a).unwrap(),
            #[allow(unreachable_patterns)]
            _ => unreachable!(),
        }
        std::fs::read_to_string(out).unwrap()
    };
    let a = run("a.jsonl", &[]);
    let b = run("b.jsonl", &[]);
    assert_eq!(a, b);
    let lines: Vec<&str> = a.lines().collect();
    assert_eq!(lines.len(), 1 + 20 * 2);
    let header: serde_json::Value = serde_json::from_str(lines[0]).unwrap();
    assert_eq!(header["scene"]["name"], "pair");
    assert_eq!(header["scene"]["cameras"][1]["width"], 1280);
    for (k, line) in lines[1..].iter().enumerate() {
        let batch: Batch = serde_json::from_str(line).unwrap();
        assert_eq!(batch.frame_id, (k / 2) as u64);
        assert_eq!(batch.camera, ["south", "west"][k % 2]);
    }
    assert!(a.contains("\"id\":"));
    // the shared reader accepts it and sees what the library simulates
    let rec = crossview_data::recording::read_recording(dir.path().join("a.jsonl")).unwrap();
    let mut cfg = SimConfig::preset("pair").unwrap();
    cfg.frames = 20;
    cfg.seed = 5;
    assert_eq!(rec, simulate(&cfg).unwrap());
    let no_ids = run("c.jsonl", &["--no-ids", "--appearance-dim", "8"]);
    assert!(!no_ids.contains("\"id\":"));
    assert!(no_ids.contains("\"appearance\":"));
}

#[test]
fn cli_reads_a_scene_file_and_writes_one_back() {
    let dir = tempfile::tempdir().unwrap();
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/corridor3.json");
    let out = dir.path().join("r.jsonl");
    let dumped = dir.path().join("scene.json");
    let cli = <crossview::cli::Cli as clap::Parser>::try_parse_from([
        "crossview",
        "simulate",
        "--scene",
        scene,
        "--frames",
        "15",
        "--density",
        "0.2",
        "--clean",
        "--out",
        out.to_str().unwrap(),
        "--write-scene",
        dumped.to_str().unwrap(),
    ])
    .unwrap();
    match cli.command {
        crossview::cli::Command::Simulate(a) => crossview::cli::simulate::run(a).unwrap(),
        #[allow(unreachable_patterns)]
        _ => unreachable!(),
    }
    let rec = crossview_data::recording::read_recording(&out).unwrap();
    assert_eq!(rec.scene.name, "corridor3");
    assert_eq!(rec.scene.cameras.len(), 3);
    assert_eq!(rec.frames.len(), 15);
    assert!(rec.num_boxes() > 15 * 3 * 5, "{} boxes", rec.num_boxes());
    // clean detector: score 1 and an id on every box
    assert!(rec.frames.iter().all(|f| {
        f.views
            .iter()
            .flatten()
            .flatten()
            .all(|d| d.score == 1.0 && d.id.is_some())
    }));
    let back = crossview_data::sim::SceneConfig::from_json_file(&dumped).unwrap();
    assert_eq!(
        back,
        crossview_data::sim::SceneConfig::from_json_file(std::path::Path::new(scene)).unwrap()
    );
    // a broken scene file is reported with its name
    let bad = dir.path().join("bad.json");
    std::fs::write(
        &bad,
        "{\"name\": \"x\", \"area\": [5, 5], \"cameras\": [{\"name\": \"a\"}]}",
    )
    .unwrap();
    let err = crossview_data::sim::SceneConfig::from_json_file(&bad)
        .unwrap_err()
        .to_string();
    assert!(err.contains("bad.json"), "{err}");
}

mod props {
    use crossview_data::sim::detector::detect;
    use crossview_data::sim::render::{RenderConfig, render_camera};
    use crossview_data::sim::{CameraConfig, DetectorNoise, Person};
    use proptest::prelude::*;
    use rand::SeedableRng;

    fn camera(z: f64, yaw: f64, pitch: f64, f: f64) -> crossview_data::sim::Camera {
        CameraConfig {
            name: "c".into(),
            position: [0.0, 0.0, z],
            yaw_deg: Some(yaw),
            pitch_deg: Some(pitch),
            look_at: None,
            focal_px: f,
            width: 1280,
            height: 720,
            principal: None,
        }
        .build("camera")
        .unwrap()
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// Any ground point the camera sees maps back to itself.
        #[test]
        fn ground_point_inverts_projection(
            z in 0.5f64..10.0, yaw in -180.0f64..180.0, pitch in 1.0f64..80.0,
            f in 200.0f64..3000.0, x in -30.0f64..30.0, y in -30.0f64..30.0,
        ) {
            let cam = camera(z, yaw, pitch, f);
            if let Some(px) = cam.project([x, y, 0.0]) {
                let g = cam.ground_point(px[0], px[1]).unwrap();
                prop_assert!((g[0] - x).abs() < 1e-6 * (1.0 + x.abs()) && (g[1] - y).abs() < 1e-6 * (1.0 + y.abs()));
            }
        }

        /// Whatever the scene and noise, emitted boxes pass the shared validation and lie in
        /// the image.
        #[test]
        fn emitted_boxes_are_always_valid(
            z in 0.5f64..10.0, yaw in -180.0f64..180.0, pitch in -10.0f64..80.0,
            people in proptest::collection::vec((-20.0f64..20.0, -20.0f64..20.0, 1.5f64..1.95), 0..25),
            jitter in 0.0f64..0.5, fp in 0.0f64..5.0, dup in 0.0f64..1.0, seed in 0u64..1000,
        ) {
            let cam = camera(z, yaw, pitch, 900.0);
            let ps: Vec<Person> = people
                .iter()
                .enumerate()
                .map(|(i, &(x, y, h))| Person::standing(i as u64, [x, y], h, 0.5))
                .collect();
            let truth = render_camera(&cam, &ps, &RenderConfig::default());
            let noise = DetectorNoise { jitter, false_positives: fp, duplicate_rate: dup, ..DetectorNoise::default() };
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            for b in detect(&truth, 1280, 720, &noise, &mut rng) {
                let d = crossview_data::sim::detector::to_detection(&b);
                prop_assert!(d.validate("d", None).is_ok(), "{:?}", d);
                prop_assert!(d.bbox[2] <= 1280.0 && d.bbox[3] <= 720.0);
            }
        }
    }
}
