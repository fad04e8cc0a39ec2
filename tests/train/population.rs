//! Population training: halving by the label-free key drops the member that a planted bad
//! start makes worse, without labels; the same seed and population give the same model; a
//! population of one is the single run; member checkpoints resume.
use crossview_train::TrainingSet;
use crossview_train::label_free::LabelFreeScorer;
use crossview_train::member::Member;
use crossview_train::population::{
    PopulationOptions, member_dir, member_seed, run_population, train_population,
};
use crossview_train::sampler::MIN_FRAMES;
use crossview_train::trainer::{CheckpointOptions, Scoring, TrainConfig, train};
use crossview_train::validate::candidate_thresholds;

use crate::fixtures::{small_config, synthetic};

/// 64 training frames and a label-free scorer over 20 held-out ones.
fn set_and_scorer() -> (TrainingSet, LabelFreeScorer) {
    let mut set =
        TrainingSet::from_recording(&synthetic(84, 6, 11).without_ids(), MIN_FRAMES).unwrap();
    let held_out = set.split_off_tail(20);
    let scorer = LabelFreeScorer::new(held_out, candidate_thresholds(), 3).unwrap();
    (set, scorer)
}

fn recipe() -> TrainConfig {
    TrainConfig {
        val_every: 10,
        ema_decay: 0.98,
        ..small_config(60)
    }
}

fn two_halved_once() -> PopulationOptions {
    PopulationOptions {
        size: 2,
        threads: 2,
        halve_at: vec![0.5],
        keep_at_least: 1,
        window: 2,
        ensemble: 1,
    }
}

/// Member 1 starts from a learning rate a thousand times too small: it barely moves, its
/// assignments stay as inconsistent as an untrained encoder's, and the label-free key alone
/// drops it at the halving point; the winner is the member that learned.
#[test]
fn halving_drops_the_member_a_bad_start_makes_worse() {
    let (set, scorer) = set_and_scorer();
    let good = recipe();
    let bad = TrainConfig {
        lr: good.lr / 1000.0,
        seed: 99,
        ..good.clone()
    };
    let members = vec![
        Member::new(&set, &good, None).unwrap(),
        Member::new(&set, &bad, None).unwrap(),
    ];
    let scoring = Scoring {
        label_free: Some(&scorer),
        ..Scoring::default()
    };
    let none = CheckpointOptions::default();
    let out = run_population(members, scoring, &none, false, &two_halved_once()).unwrap();
    assert_eq!(out.winner, 0, "{}", out.summary());
    assert_eq!(out.members[1].dropped_at, Some(30), "{:?}", out.members);
    assert_eq!(out.members[0].dropped_at, None);
    let (good_key, bad_key) = (out.members[0].key.unwrap(), out.members[1].key.unwrap());
    assert!(good_key > bad_key, "{good_key} vs {bad_key}");
    // The dropped member stopped at the halving point; the winner trained to the end.
    assert_eq!(out.outcome.history.len(), 60);
    assert_eq!(out.finalists.len(), 1);
    assert!(out.summary().contains("member 1 dropped at epoch 30"));
}

/// Same seed, same population: the same model, bit for bit, although the members train on
/// two threads. Member seeds are derived from the run's seed, member 0's being the seed
/// itself, so a population of one is exactly the single run.
#[test]
fn same_seed_same_population_same_model_and_one_member_is_the_single_run() {
    let (set, scorer) = set_and_scorer();
    let cfg = TrainConfig {
        epochs: 30,
        ..recipe()
    };
    let none = CheckpointOptions::default();
    let run = |opts: &PopulationOptions| {
        let scoring = Scoring {
            label_free: Some(&scorer),
            ..Scoring::default()
        };
        train_population(&set, &cfg, None, scoring, &none, false, opts).unwrap()
    };
    let a = run(&two_halved_once());
    let b = run(&two_halved_once());
    assert_eq!(a.outcome.weights, b.outcome.weights);
    assert_eq!(a.members, b.members);
    assert_eq!(a.members[0].seed, cfg.seed);
    assert_eq!(a.members[1].seed, member_seed(cfg.seed, 1));
    assert_ne!(a.members[0].seed, a.members[1].seed);

    let one = run(&PopulationOptions::single());
    let scoring = Scoring {
        label_free: Some(&scorer),
        ..Scoring::default()
    };
    let single = train(&set, &cfg, scoring, &none, false).unwrap();
    assert_eq!(one.outcome.weights, single.weights);
    assert_eq!(one.outcome.best_epoch, single.best_epoch);
}

/// Every member checkpoints in its own directory with the population's report beside them;
/// a population that resumes from those checkpoints ends with the same model as one run
/// straight through.
#[test]
fn member_checkpoints_resume_to_the_same_model() {
    let (set, scorer) = set_and_scorer();
    // No learning-rate drop: the first half's schedule must not depend on the run's length.
    let cfg = TrainConfig {
        epochs: 20,
        lr_drop_at: 1.0,
        ..recipe()
    };
    let opts = PopulationOptions {
        halve_at: Vec::new(),
        ..two_halved_once()
    };
    let scoring = || Scoring {
        label_free: Some(&scorer),
        ..Scoring::default()
    };
    let none = CheckpointOptions::default();
    let straight = train_population(&set, &cfg, None, scoring(), &none, false, &opts).unwrap();

    let dir = tempfile::tempdir().unwrap();
    let ck = CheckpointOptions {
        dir: Some(dir.path().to_path_buf()),
        every: 10,
        resume: true,
        ..CheckpointOptions::default()
    };
    let half = TrainConfig {
        epochs: 10,
        ..cfg.clone()
    };
    train_population(&set, &half, None, scoring(), &ck, false, &opts).unwrap();
    assert!(member_dir(dir.path(), 0).join("state.json").is_file());
    assert!(member_dir(dir.path(), 1).join("state.json").is_file());
    assert!(dir.path().join("population.json").is_file());
    let resumed = train_population(&set, &cfg, None, scoring(), &ck, false, &opts).unwrap();
    assert_eq!(resumed.outcome.history.len(), 20);
    assert_eq!(resumed.winner, straight.winner);
    let max_diff = resumed
        .outcome
        .weights
        .blocks
        .iter()
        .zip(&straight.outcome.weights.blocks)
        .flat_map(|(x, y)| x.weight.iter().zip(&y.weight))
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, f32::max);
    assert!(max_diff < 1e-6, "resumed population differs by {max_diff}");
}

/// A population with nothing to rank its members by is refused with a clear message.
#[test]
fn a_population_without_a_score_is_refused() {
    let (set, _) = set_and_scorer();
    let cfg = recipe();
    let e = train_population(
        &set,
        &cfg,
        None,
        Scoring::default(),
        &CheckpointOptions::default(),
        false,
        &two_halved_once(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("--holdout"), "{e}");
}

/// A cloned member is independent and continues exactly: the clone and the original, advanced
/// by the same epoch with the same seed, end with the same weights, and training the clone
/// leaves the original where it was.
#[test]
fn a_cloned_member_continues_exactly_and_apart() {
    let (set, _) = set_and_scorer();
    let cfg = TrainConfig {
        epochs: 4,
        ..recipe()
    };
    let mut original = Member::new(&set, &cfg, None).unwrap();
    for _ in 0..2 {
        original.train_epoch(&|| ()).unwrap();
    }
    let untouched = original.clone_with_seed(cfg.seed).unwrap();
    let mut clone = original.clone_with_seed(cfg.seed).unwrap();
    original.train_epoch(&|| ()).unwrap();
    clone.train_epoch(&|| ()).unwrap();
    let select = crossview_train::trainer::Select::LabelFree;
    let (a, b) = (
        original.finish(select).unwrap(),
        clone.finish(select).unwrap(),
    );
    assert_eq!(a.weights, b.weights);
    let before = untouched.finish(select).unwrap();
    assert_eq!(before.best_epoch, 2);
    assert_ne!(before.weights, a.weights);
}
