//! The replayed workload: a SPEC §7 recording (or simulator output) grouped into frames, each
//! frame the batches of its cameras in camera order.
use std::collections::BTreeMap;
use std::io::BufRead;
use std::path::Path;

use anyhow::{Context, bail};
use crossview_core::{Batch, SceneSpec};
use crossview_data::RecordingReader;

/// One frame of the recording: the batch of every camera that reported it, as
/// `(camera index, batch)`, sorted by camera index.
#[derive(Debug, Clone)]
pub struct FrameBatches {
    pub frame_id: u64,
    pub batches: Vec<(usize, Batch)>,
}

/// A recording in replay order.
#[derive(Debug, Clone)]
pub struct Workload {
    pub scene: SceneSpec,
    pub frames: Vec<FrameBatches>,
}

impl Workload {
    /// Reads a JSONL recording; errors name the file and line.
    pub fn load(path: &Path) -> anyhow::Result<Self> {
        let file = std::fs::File::open(path)
            .with_context(|| format!("cannot open recording {}", path.display()))?;
        Self::from_reader(std::io::BufReader::new(file), &path.display().to_string())
    }

    /// Parses a recording from any reader with the library's validating reader (header,
    /// known cameras, no second batch per camera and frame, valid boxes); `name` labels error
    /// messages.
    pub fn from_reader(reader: impl BufRead, name: &str) -> anyhow::Result<Self> {
        let batches = RecordingReader::new(reader, name)?;
        let scene = batches.scene().clone();
        let mut frames: BTreeMap<u64, Vec<(usize, Batch)>> = BTreeMap::new();
        for batch in batches {
            let batch = batch?;
            let cam = scene.camera_index(&batch.camera)?;
            frames.entry(batch.frame_id).or_default().push((cam, batch));
        }
        if frames.is_empty() {
            bail!("{name}: recording has a scene header but no batches");
        }
        let frames = frames
            .into_iter()
            .map(|(frame_id, mut batches)| {
                batches.sort_by_key(|(c, _)| *c);
                FrameBatches { frame_id, batches }
            })
            .collect();
        Ok(Workload { scene, frames })
    }

    /// Frame-id offset added on each pass when the recording is replayed in a loop, so
    /// every pass gets fresh, increasing frame ids.
    pub fn loop_span(&self) -> u64 {
        self.frames.last().map_or(1, |f| f.frame_id + 1)
    }

    /// Total number of batches in one pass.
    pub fn num_batches(&self) -> usize {
        self.frames.iter().map(|f| f.batches.len()).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const REC: &str = r#"{"scene": {"name": "lab", "cameras": [{"name": "a", "width": 640, "height": 480}, {"name": "b", "width": 640, "height": 480}]}}
{"camera": "b", "frame_id": 3, "detections": []}
{"camera": "a", "frame_id": 3, "detections": [{"bbox": [1, 2, 30, 40]}]}
{"camera": "a", "frame_id": 1, "detections": []}
"#;

    #[test]
    fn groups_batches_by_frame_in_camera_order() {
        let w = Workload::from_reader(REC.as_bytes(), "t").unwrap();
        assert_eq!(w.scene.name, "lab");
        assert_eq!(w.frames.len(), 2);
        assert_eq!(w.frames[0].frame_id, 1);
        let cams: Vec<usize> = w.frames[1].batches.iter().map(|(c, _)| *c).collect();
        assert_eq!(cams, vec![0, 1]);
        assert_eq!(w.num_batches(), 3);
        assert_eq!(w.loop_span(), 4);
    }

    #[test]
    fn rejects_unknown_camera_and_duplicates() {
        let bad = REC.replace("\"camera\": \"b\"", "\"camera\": \"zz\"");
        let e = Workload::from_reader(bad.as_bytes(), "t").unwrap_err();
        assert!(format!("{e:#}").contains("zz"), "{e:#}");
        let dup = format!(
            "{REC}{}\n",
            r#"{"camera": "a", "frame_id": 1, "detections": []}"#
        );
        let e = Workload::from_reader(dup.as_bytes(), "t").unwrap_err();
        assert!(format!("{e:#}").contains("duplicate batch"), "{e:#}");
        assert!(Workload::from_reader("".as_bytes(), "t").is_err());
    }
}
