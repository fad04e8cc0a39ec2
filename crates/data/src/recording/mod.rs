//! The SPEC §7 JSONL recording: a scene header line, then one camera batch per line. **[ours]**
//! The header may also declare the recording's frame rate, `{"scene": {...}, "fps": 10}`
//! ([`Recording::fps`]); a rate that is no frame rate is an error on line 1.
//!
//! - [`read_recording`] loads a whole recording into a [`Recording`]: one file, stdin (path
//!   `-`) or a directory; [`read_recordings`] several of them as one recording.
//! - [`RecordingReader`] streams it: the header first, then an iterator of validated
//!   [`Batch`]es, so huge files never sit in memory.
//! - [`RecordingWriter`] / [`write_recording`] write the same format back.
//!
//! Every problem in a file is an [`Error::Format`] naming the source, the 1-based line and the
//! problem (malformed JSON, missing header, unknown camera, duplicate batch, invalid detection,
//! inconsistent appearance length).
//!
//! Boxes that overlap their image's edge are clipped to the image
//! ([`Detection::clip_to_image`](crossview_core::Detection::clip_to_image), the one rule shared with the server) and counted in
//! [`ReadStats::clipped_boxes`]. A lenient reader (the trainer's
//! default) skips a broken box or a broken line with a count instead of failing: real
//! detector output is careless, and one bad box must not abort a 71,000-box recording.
//!
//! **Several files, directories, torn tails.** A recording may span several files (as
//! `crossview serve --record` writes them, rotated): [`read_recordings`] takes files and
//! directories — a directory stands for every `*.jsonl` file below it, recursively (symbolic
//! links to directories are not followed), in path order (the server's file names sort by
//! start time) — and reads them, in the order given, as one recording. Every file starts with
//! its own scene header and all must declare the same scene (the same cameras; their clock
//! offsets may differ, and each file's batches are grouped by its own header's, as a server
//! whose `--auto-align` changed an offset wrote them); a frame may be spread over several
//! files (a rotation between its cameras' batches), but a camera twice for one frame, in one
//! file or two, is still a duplicate. The **last line of each file**, when it has no newline at
//! its end and is not complete JSON (a crash cut it short while it was written), is **torn**:
//! it is dropped and counted ([`ReadStats::torn_lines`], one `warn` log with the count), never
//! an error; a file that holds nothing else (a torn header, or no bytes at all) adds nothing.
//! A broken line anywhere else, or a last line that ends with its newline, stays an error
//! naming its file and line.

mod assemble;
mod files;
mod reader;
mod writer;

use std::collections::HashSet;
use std::ops::RangeBounds;

use serde::{Deserialize, Serialize};

use crossview_core::{Batch, Frame, SceneSpec};
use crossview_core::{Error, Result};

pub use files::{read_recording, read_recording_with, read_recordings, recording_files};
pub use reader::{ReadStats, RecordingReader};
pub use writer::{RecordingWriter, write_recording};

use assemble::{FrameAssembler, Inserted};
use reader::AppearanceLen;

/// A whole recording in memory: the scene and its frames sorted by frame id.
/// `frames[k].views[c]` is `None` when camera `c` sent no batch for that frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Recording {
    pub scene: SceneSpec,
    pub frames: Vec<Frame>,
    /// **[ours]** The frame rate its header declares (frames per second of its frame ids;
    /// `crossview simulate` and the WILDTRACK importers write it), `None` when it declares
    /// none.
    pub fps: Option<f64>,
}

/// The first line of a recording: `{"scene": {...}}`, with an optional `"fps"`.
#[derive(Debug, Serialize, Deserialize)]
struct Header {
    scene: SceneSpec,
    #[serde(default)]
    fps: Option<f64>,
}

/// Checks a scene is usable: a name, at least one camera, unique camera names, positive sizes.
fn validate_scene(scene: &SceneSpec) -> std::result::Result<(), String> {
    if scene.name.is_empty() {
        return Err("scene.name is empty".into());
    }
    if scene.cameras.is_empty() {
        return Err("scene.cameras is empty".into());
    }
    let mut names = HashSet::new();
    for (i, cam) in scene.cameras.iter().enumerate() {
        if cam.name.is_empty() {
            return Err(format!("scene.cameras[{i}].name is empty"));
        }
        if !names.insert(cam.name.as_str()) {
            return Err(format!(
                "scene.cameras[{i}].name '{}' is used twice",
                cam.name
            ));
        }
        if cam.width == 0 || cam.height == 0 {
            return Err(format!(
                "scene.cameras[{i}] ('{}') has a zero image size {}x{}",
                cam.name, cam.width, cam.height
            ));
        }
    }
    Ok(())
}

impl Recording {
    /// Assembles frames from batches in any order: frames sorted by frame id, `views[c]` is
    /// `None` where camera `c` sent nothing. Fails on an invalid scene, an unknown camera
    /// ([`Error::UnknownCamera`]), a second batch for the same camera and frame
    /// ([`Error::DuplicateBatch`]) or an invalid detection / inconsistent appearance length
    /// ([`Error::InvalidArgument`], field `<camera>@<frame>.detections[i]...`). Boxes
    /// overlapping the image edge are clipped ([`Detection::clip_to_image`](crossview_core::Detection::clip_to_image)).
    pub fn from_batches(
        scene: SceneSpec,
        batches: impl IntoIterator<Item = Batch>,
    ) -> Result<Recording> {
        validate_scene(&scene).map_err(|m| Error::invalid("scene", m))?;
        let mut appearance = AppearanceLen::default();
        let mut assembler = FrameAssembler::new(&scene);
        for mut batch in batches {
            let cam = scene.camera_index(&batch.camera)?;
            for (i, det) in batch.detections.iter_mut().enumerate() {
                appearance
                    .check(i, det, &scene.cameras[cam])
                    .map_err(|e| match e {
                        Error::InvalidArgument { field, reason } => Error::InvalidArgument {
                            field: format!("{}@{}.{field}", batch.camera, batch.frame_id),
                            reason,
                        },
                        other => other,
                    })?;
            }
            match assembler.insert(cam, batch.frame_id, batch.detections) {
                Inserted::Added => {}
                Inserted::Duplicate => {
                    return Err(Error::DuplicateBatch {
                        scene: scene.name.clone(),
                        camera: batch.camera,
                        frame_id: batch.frame_id,
                    });
                }
                Inserted::OutOfRange => {
                    return Err(Error::invalid(
                        format!("{}@{}", batch.camera, batch.frame_id),
                        "the frame id less the camera's clock offset is out of range",
                    ));
                }
            }
        }
        Ok(Recording {
            frames: assembler.finish(),
            scene,
            fps: None,
        })
    }

    /// The same recording with every ground-truth id removed (what training may see).
    pub fn without_ids(&self) -> Recording {
        let mut out = self.clone();
        for det in out
            .frames
            .iter_mut()
            .flat_map(|f| f.views.iter_mut().flatten())
            .flat_map(|v| v.iter_mut())
        {
            det.id = None;
        }
        out
    }

    /// The frames whose id lies in `range` (e.g. `1440..=1795`), same scene.
    pub fn filter_frames(&self, range: impl RangeBounds<u64>) -> Recording {
        Recording {
            scene: self.scene.clone(),
            fps: self.fps,
            frames: self
                .frames
                .iter()
                .filter(|f| range.contains(&f.frame_id))
                .cloned()
                .collect(),
        }
    }

    /// Total number of boxes over all frames and views.
    pub fn num_boxes(&self) -> usize {
        self.frames.iter().map(Frame::num_boxes).sum()
    }

    /// The frame ids, ascending.
    pub fn frame_ids(&self) -> Vec<u64> {
        self.frames.iter().map(|f| f.frame_id).collect()
    }

    /// The recording as batches, frame by frame in camera order: a camera that reported
    /// nobody gives an empty list; a camera that did not report is omitted.
    pub fn batches(&self) -> impl Iterator<Item = Batch> + '_ {
        self.frames.iter().flat_map(move |f| {
            f.views.iter().enumerate().filter_map(move |(c, v)| {
                v.as_ref().map(|dets| {
                    let cam = &self.scene.cameras[c];
                    Batch {
                        camera: cam.name.clone(),
                        // The camera's own id: the frame's plus its clock offset.
                        frame_id: f.frame_id.saturating_add_signed(cam.offset),
                        time: None,
                        detections: dets.clone(),
                    }
                })
            })
        })
    }
}
