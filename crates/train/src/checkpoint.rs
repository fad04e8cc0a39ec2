//! Checkpoints: model parameters, Adam moments, the moving average and the best weights in one
//! safetensors file, plus a JSON file with the counters and history. Written atomically.
use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::adam::Adam;
use crate::config::TrainConfig;
use crate::label_free::LabelFreeScores;
use crate::model::{TrainModel, ce};
use crate::pseudo::PseudoLabels;
use crate::state::{Best, EpochRecord, RunState, ValScores};
use crossview_core::{Error, Result};

const TENSORS: &str = "state.safetensors";
const META: &str = "state.json";

#[derive(Debug, Serialize, Deserialize)]
struct Meta {
    config: TrainConfig,
    num_cameras: usize,
    epoch: usize,
    adam_steps: u64,
    train_seconds: f64,
    history: Vec<EpochRecord>,
    best: Option<BestMeta>,
    #[serde(default)]
    pseudo: Option<PseudoLabels>,
    #[serde(default)]
    stage_steps: u64,
}

#[derive(Debug, Serialize, Deserialize)]
struct BestMeta {
    epoch: usize,
    val: Option<ValScores>,
    label_free: Option<LabelFreeScores>,
}

/// True when `dir` holds a checkpoint.
pub fn exists(dir: &Path) -> bool {
    dir.join(TENSORS).is_file() && dir.join(META).is_file()
}

/// Saves the run state to `dir` (created if missing).
pub(crate) fn save(dir: &Path, cfg: &TrainConfig, st: &RunState) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let mut tensors: HashMap<String, Tensor> = HashMap::new();
    let fourier = |m: &TrainModel| {
        Tensor::from_slice(&m.fourier, (2, m.config.fourier_features), &Device::Cpu)
    };
    tensors.insert("fourier".into(), fourier(&st.model).map_err(ce)?);
    for (i, (name, var)) in st.model.named_vars().into_iter().enumerate() {
        tensors.insert(format!("param.{name}"), var.as_tensor().clone());
        tensors.insert(format!("adam_m.{name}"), st.adam.m[i].clone());
        tensors.insert(format!("adam_v.{name}"), st.adam.v[i].clone());
    }
    if let Some(ema) = &st.ema {
        for (name, var) in ema.named_vars() {
            if !name.starts_with("decoder") {
                tensors.insert(format!("ema.{name}"), var.as_tensor().clone());
            }
        }
    }
    if let Some(b) = &st.best {
        let bm = TrainModel::from_weights(&b.weights, 0)?;
        for (name, var) in bm.named_vars() {
            if !name.starts_with("decoder") {
                tensors.insert(format!("best.{name}"), var.as_tensor().clone());
            }
        }
    }
    let meta = Meta {
        config: cfg.clone(),
        num_cameras: st.model.num_cameras,
        epoch: st.epoch,
        adam_steps: st.adam.t,
        train_seconds: st.train_seconds,
        history: st.history.clone(),
        best: st.best.as_ref().map(|b| BestMeta {
            epoch: b.epoch,
            val: b.val,
            label_free: b.label_free,
        }),
        pseudo: st.pseudo.clone(),
        stage_steps: st.stage_steps,
    };
    let tmp = dir.join(format!("{TENSORS}.tmp"));
    candle_core::safetensors::save(&tensors, &tmp).map_err(ce)?;
    rename(&tmp, &dir.join(TENSORS))?;
    let tmp = dir.join(format!("{META}.tmp"));
    let json = serde_json::to_vec_pretty(&meta)
        .map_err(|e| Error::Training(format!("checkpoint metadata: {e}")))?;
    std::fs::write(&tmp, json).map_err(|e| Error::io(&tmp, e))?;
    rename(&tmp, &dir.join(META))
}

fn rename(from: &Path, to: &Path) -> Result<()> {
    std::fs::rename(from, to).map_err(|e| Error::io(PathBuf::from(to), e))
}

/// Loads the run state from `dir`; the encoder shape and camera count must match `cfg`.
pub fn load(dir: &Path, cfg: &TrainConfig, num_cameras: usize) -> Result<RunState> {
    let meta_path = dir.join(META);
    let bytes = std::fs::read(&meta_path).map_err(|e| Error::io(&meta_path, e))?;
    let meta: Meta = serde_json::from_slice(&bytes).map_err(|e| Error::Format {
        source_name: meta_path.display().to_string(),
        line: 0,
        message: e.to_string(),
    })?;
    if meta.config.encoder() != cfg.encoder() || meta.num_cameras != num_cameras {
        return Err(Error::Training(format!(
            "checkpoint in {} was made for encoder {:?} with {} cameras, not {:?} with {}",
            dir.display(),
            meta.config.encoder(),
            meta.num_cameras,
            cfg.encoder(),
            num_cameras
        )));
    }
    let tpath = dir.join(TENSORS);
    let t = candle_core::safetensors::load(&tpath, &Device::Cpu).map_err(ce)?;
    let get = |k: &str| {
        t.get(k).cloned().ok_or_else(|| {
            Error::Training(format!("checkpoint {} lacks tensor '{k}'", tpath.display()))
        })
    };
    let mut model = TrainModel::new(cfg.encoder(), num_cameras, cfg.seed)?;
    model.fourier = get("fourier")?
        .flatten_all()
        .and_then(|x| x.to_vec1::<f32>())
        .map_err(ce)?;
    let mut m = Vec::new();
    let mut v = Vec::new();
    for (name, var) in model.named_vars() {
        let p = get(&format!("param.{name}"))?;
        if p.dims() != var.dims() {
            return Err(Error::Training(format!(
                "checkpoint tensor '{name}' has shape {:?}, expected {:?}",
                p.dims(),
                var.dims()
            )));
        }
        var.set(&p).map_err(ce)?;
        m.push(get(&format!("adam_m.{name}"))?);
        v.push(get(&format!("adam_v.{name}"))?);
    }
    let mut adam = Adam::new(model.named_vars(), cfg.lr)?;
    adam.m = m;
    adam.v = v;
    adam.t = meta.adam_steps;
    let ema = if cfg.ema_decay > 0.0 {
        let em = TrainModel::from_weights(&model.to_weights()?, cfg.seed)?;
        for (name, var) in em.named_vars() {
            if !name.starts_with("decoder") {
                var.set(&get(&format!("ema.{name}"))?).map_err(ce)?;
            }
        }
        Some(em)
    } else {
        None
    };
    let best = match meta.best {
        Some(b) => {
            let bm = TrainModel::new(cfg.encoder(), num_cameras, cfg.seed)?;
            for (name, var) in bm.named_vars() {
                if !name.starts_with("decoder") {
                    var.set(&get(&format!("best.{name}"))?).map_err(ce)?;
                }
            }
            let mut bm = bm;
            bm.fourier = model.fourier.clone();
            Some(Best {
                weights: bm.to_weights()?,
                epoch: b.epoch,
                val: b.val,
                label_free: b.label_free,
            })
        }
        None => None,
    };
    Ok(RunState {
        model,
        adam,
        ema,
        pseudo: meta.pseudo,
        stage_steps: meta.stage_steps,
        epoch: meta.epoch,
        history: meta.history,
        best,
        train_seconds: meta.train_seconds,
    })
}
