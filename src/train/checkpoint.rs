//! Checkpoints: model parameters, Adam moments and the best validated weights in one
//! safetensors file, plus a JSON file with the counters and history. Written atomically.
use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::train::adam::Adam;
use crate::train::model::{TrainModel, ce};
use crate::train::trainer::{EpochRecord, RunState, TrainConfig, ValScores};
use crate::{Error, Result};

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
    best: Option<(ValScores, usize)>,
}

/// True when `dir` holds a checkpoint.
pub fn exists(dir: &Path) -> bool {
    dir.join(TENSORS).is_file() && dir.join(META).is_file()
}

/// Saves the run state to `dir` (created if missing).
pub fn save(dir: &Path, cfg: &TrainConfig, st: &RunState) -> Result<()> {
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
    if let Some((w, _, _)) = &st.best {
        let bm = TrainModel::from_weights(w, 0)?;
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
        best: st.best.as_ref().map(|(_, s, e)| (*s, *e)),
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
    let best = match meta.best {
        Some((scores, epoch)) => {
            let bm = TrainModel::new(cfg.encoder(), num_cameras, cfg.seed)?;
            for (name, var) in bm.named_vars() {
                if !name.starts_with("decoder") {
                    var.set(&get(&format!("best.{name}"))?).map_err(ce)?;
                }
            }
            let mut bm = bm;
            bm.fourier = model.fourier.clone();
            Some((bm.to_weights()?, scores, epoch))
        }
        None => None,
    };
    Ok(RunState {
        model,
        adam,
        epoch: meta.epoch,
        history: meta.history,
        best,
        train_seconds: meta.train_seconds,
    })
}
