//! What the benchmark drivers share: pushing a recording's frames to a real server as cameras
//! send them, and the arguments of the runs in which one camera moves.
use std::path::PathBuf;

use crossview_core::{Batch, Frame};
use rand::Rng;
use rand::seq::SliceRandom;

/// The arguments of a run in which one camera of a recording moves.
#[derive(Debug, clap::Args)]
pub struct MovedCamera {
    /// The scene's model file.
    #[arg(long)]
    pub model: PathBuf,
    /// A recording with ground-truth ids (sent without them).
    #[arg(long)]
    pub data: PathBuf,
    /// The camera that moves.
    #[arg(long)]
    pub camera: String,
    /// First frame id with the camera moved.
    #[arg(long)]
    pub moved_at: u64,
}

/// Pushes one frame to `url` (a scene's `/batches`) over HTTP as real cameras send it: one batch
/// per camera, in an order `rng` shuffles, ground-truth ids stripped; camera `silent`, if any,
/// sends an empty batch. Returns the refusals (status and body of every answer but 202).
pub async fn push_frame(
    http: &reqwest::Client,
    url: &str,
    names: &[String],
    frame: &Frame,
    rng: &mut impl Rng,
    silent: Option<usize>,
) -> reqwest::Result<Vec<String>> {
    let mut order: Vec<usize> = (0..names.len()).collect();
    order.shuffle(rng);
    let mut refused = Vec::new();
    for c in order {
        let mut detections = frame.views[c].clone().unwrap_or_default();
        if silent == Some(c) {
            detections.clear();
        }
        detections.iter_mut().for_each(|d| d.id = None);
        let batch = Batch {
            camera: names[c].clone(),
            frame_id: frame.frame_id,
            time: None,
            detections,
        };
        let r = http.post(url).json(&batch).send().await?;
        if r.status().as_u16() != 202 {
            refused.push(format!(
                "{}: {}",
                r.status(),
                r.text().await.unwrap_or_default()
            ));
        }
    }
    Ok(refused)
}
