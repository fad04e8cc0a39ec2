//! Writing a recording back in the same format.
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use serde::Serialize;

use crossview_core::types::{BatchLine, HeaderLine};
use crossview_core::{Batch, Frame, SceneSpec};
use crossview_core::{Error, Result};

use super::{Recording, validate_scene};

/// Writes a recording: the header on creation, then batch lines; buffered. Call
/// [`RecordingWriter::finish`] to flush and surface write errors.
pub struct RecordingWriter<W: Write> {
    dest_name: String,
    writer: BufWriter<W>,
    scene: SceneSpec,
}

impl RecordingWriter<Box<dyn Write>> {
    /// Creates (truncates) `path` (`-` = stdout) and writes the header, with the frame rate
    /// `fps` when it is known.
    pub fn create(path: impl AsRef<Path>, scene: &SceneSpec, fps: Option<f64>) -> Result<Self> {
        let path = path.as_ref();
        let inner: Box<dyn Write> = if path == Path::new("-") {
            Box::new(std::io::stdout())
        } else {
            Box::new(File::create(path).map_err(|e| Error::io(path, e))?)
        };
        RecordingWriter::new(inner, path.display().to_string(), scene, fps)
    }
}

impl<W: Write> RecordingWriter<W> {
    /// Wraps a writer (`dest_name` names it in errors) and writes the header line, with the
    /// frame rate `fps` when it is known.
    pub fn new(
        writer: W,
        dest_name: impl Into<String>,
        scene: &SceneSpec,
        fps: Option<f64>,
    ) -> Result<Self> {
        validate_scene(scene).map_err(|m| Error::invalid("scene", m))?;
        if let Some(fps) = fps {
            crossview_core::types::check_fps(fps).map_err(|m| Error::invalid("fps", m))?;
        }
        let mut this = RecordingWriter {
            dest_name: dest_name.into(),
            writer: BufWriter::new(writer),
            scene: scene.clone(),
        };
        this.write_json(&HeaderLine { scene, fps })?;
        Ok(this)
    }

    fn write_json<T: Serialize>(&mut self, value: &T) -> Result<()> {
        let io_err = |e: std::io::Error| Error::io(&self.dest_name, e);
        serde_json::to_writer(&mut self.writer, value)
            .map_err(|e| io_err(std::io::Error::other(e)))?;
        self.writer.write_all(b"\n").map_err(io_err)
    }

    /// Writes one batch line. The camera must belong to the scene.
    pub fn write_batch(&mut self, batch: &Batch) -> Result<()> {
        self.scene.camera_index(&batch.camera)?;
        self.write_json(batch)
    }

    /// Writes every reported view of `frame` (in camera order) as a batch line.
    pub fn write_frame(&mut self, frame: &Frame) -> Result<()> {
        if frame.views.len() != self.scene.cameras.len() {
            return Err(Error::invalid(
                format!("frame {}.views", frame.frame_id),
                format!(
                    "has {} views, scene '{}' has {} cameras",
                    frame.views.len(),
                    self.scene.name,
                    self.scene.cameras.len()
                ),
            ));
        }
        for (c, view) in frame.views.iter().enumerate() {
            if let Some(dets) = view {
                let cam = &self.scene.cameras[c];
                let camera = cam.name.clone();
                // The camera's own id: the frame's plus its clock offset.
                let frame_id = frame
                    .frame_id
                    .checked_add_signed(cam.offset)
                    .ok_or_else(|| {
                        Error::invalid(
                            format!("frame {}", frame.frame_id),
                            format!("plus camera '{camera}''s clock offset is out of range"),
                        )
                    })?;
                self.write_json(&BatchLine {
                    camera: &camera,
                    frame_id,
                    time: None,
                    detections: dets,
                })?;
            }
        }
        Ok(())
    }

    /// Flushes and returns the inner writer.
    pub fn finish(self) -> Result<W> {
        let name = self.dest_name;
        self.writer
            .into_inner()
            .map_err(|e| Error::io(&name, e.into_error()))
    }
}

/// Writes a whole recording to `path` (`-` = stdout).
pub fn write_recording(path: impl AsRef<Path>, recording: &Recording) -> Result<()> {
    let mut writer = RecordingWriter::create(path, &recording.scene, recording.fps)?;
    for frame in &recording.frames {
        writer.write_frame(frame)?;
    }
    writer.finish()?;
    Ok(())
}
