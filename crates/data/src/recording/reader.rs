//! Streaming reader: the header, then validated batches one at a time.
use std::collections::HashMap;
use std::fs::File;
use std::io::{BufRead, BufReader, Read};
use std::path::Path;

use crossview_core::capture::{CameraPhase, CaptureTime, Ticks};
use crossview_core::{Batch, CameraSpec, Detection, SceneSpec};
use crossview_core::{Error, Result};

use super::{Header, validate_scene};

/// Tracks the appearance-vector length of a scene: fixed by the first vector seen.
#[derive(Debug, Default, Clone, Copy)]
pub(super) struct AppearanceLen(Option<usize>);

impl AppearanceLen {
    /// Validates one detection (field `detections[i]...`), checks that all appearance vectors
    /// share one length and clips the box to `cam`'s image; returns whether it was clipped.
    pub(super) fn check(
        &mut self,
        i: usize,
        det: &mut Detection,
        cam: &CameraSpec,
    ) -> Result<bool> {
        let field = format!("detections[{i}]");
        det.validate(&field, self.0)?;
        let clipped = det.clip_to_image(&field, cam)?;
        if self.0.is_none() {
            self.0 = det.appearance.as_ref().map(Vec::len);
        }
        Ok(clipped)
    }
}

/// What a reader clipped and skipped so far.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct ReadStats {
    /// Boxes clipped to their image (they overlapped its edge).
    pub clipped_boxes: usize,
    /// Broken boxes skipped (lenient readers only): NaN, inverted, entirely outside the
    /// image, bad score or appearance.
    pub skipped_boxes: usize,
    /// Broken lines skipped (lenient readers only): malformed JSON, unknown camera,
    /// duplicate batch.
    pub skipped_lines: usize,
    /// Torn last lines dropped: a file's last line without its newline that is not
    /// complete JSON (left by a crash while it was written; see the module docs).
    pub torn_lines: usize,
    /// Empty files skipped (several files or a directory only).
    pub empty_files: usize,
    /// The first problem skipped, for the summary.
    pub first_problem: Option<String>,
}

impl ReadStats {
    pub(super) fn skipped(&mut self, problem: &Error) {
        self.first_problem
            .get_or_insert_with(|| problem.to_string());
    }
}

/// Streams a recording: reads and validates the header on construction, then yields one
/// validated [`Batch`] per line. Blank lines are skipped (they still count for line numbers).
///
/// Validation per batch: known camera, no second batch for the same camera and frame, every
/// detection valid ([`Detection::validate`]) and all appearance vectors of the same length.
/// After the first error the iterator is fused (yields `None`). A
/// lenient reader (crate-internal, `lenient()`) skips broken boxes and lines instead (counted in
/// [`stats`](Self::stats)); only I/O errors end it.
pub struct RecordingReader<R> {
    source_name: String,
    reader: R,
    line_no: usize,
    buf: Vec<u8>,
    /// The last line read had no newline at its end (so it was the input's last).
    unterminated: bool,
    /// The last line read was not complete JSON (or not UTF-8).
    not_json: bool,
    scene: SceneSpec,
    fps: Option<f64>,
    /// Per camera, its clock offset for capture times (declared, or followed from its times
    /// as the server follows it: [`CameraPhase`]).
    phases: Vec<CameraPhase>,
    pub(super) appearance: AppearanceLen,
    /// Per frame id, a bitset of the cameras that reported it (duplicate detection);
    /// `None` when the check is switched off.
    seen: Option<HashMap<u64, Box<[u64]>>>,
    done: bool,
    lenient: bool,
    pub(super) stats: ReadStats,
}

/// What the start of an input holds.
pub(super) enum Start<R> {
    Reader(Box<RecordingReader<R>>),
    /// No line at all (the source's name).
    Empty(String),
    /// Only a torn header (its error, for when that is all there is).
    TornHeader(Error),
}

impl RecordingReader<BufReader<Box<dyn Read>>> {
    /// Opens `path` (`-` = stdin) and reads its header.
    pub fn open(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let inner: Box<dyn Read> = if path == Path::new("-") {
            Box::new(std::io::stdin())
        } else {
            Box::new(File::open(path).map_err(|e| Error::io(path, e))?)
        };
        RecordingReader::new(BufReader::new(inner), path.display().to_string())
    }
}

impl<R: BufRead> RecordingReader<R> {
    /// Wraps a reader; `source_name` names it in error messages. Reads and validates the
    /// header line.
    pub fn new(reader: R, source_name: impl Into<String>) -> Result<Self> {
        match Self::start(reader, source_name.into())? {
            Start::Reader(r) => Ok(*r),
            Start::Empty(name) => Err(Self::empty_error(name)),
            Start::TornHeader(e) => Err(e),
        }
    }

    /// Reads the header: a reader, or what the input holds instead of a header.
    pub(super) fn start(reader: R, source_name: String) -> Result<Start<R>> {
        let mut this = RecordingReader {
            source_name,
            reader,
            line_no: 0,
            buf: Vec::new(),
            unterminated: false,
            not_json: false,
            scene: SceneSpec {
                name: String::new(),
                cameras: Vec::new(),
            },
            fps: None,
            phases: Vec::new(),
            appearance: AppearanceLen::default(),
            seen: Some(HashMap::new()),
            done: false,
            lenient: false,
            stats: ReadStats::default(),
        };
        let Some(line) = this.next_line()? else {
            return Ok(Start::Empty(this.source_name));
        };
        let header: Header = match line.map(|l| (serde_json::from_str::<Header>(&l), l)) {
            Ok((Ok(h), _)) => h,
            Ok((Err(e), _)) => {
                let err = this.format_err(
                    this.line_no,
                    format!(
                        "invalid scene header (expected {{\"scene\": {{\"name\", \"cameras\"}}}}, optionally with \"fps\": frames per second): {e}"
                    ),
                );
                if this.unterminated && (e.is_syntax() || e.is_eof()) {
                    return Ok(Start::TornHeader(err));
                }
                return Err(err);
            }
            Err(e) if this.unterminated => return Ok(Start::TornHeader(e)),
            Err(e) => return Err(e),
        };
        validate_scene(&header.scene)
            .map_err(|m| this.format_err(this.line_no, format!("invalid scene header: {m}")))?;
        if let Some(fps) = header.fps {
            crossview_core::types::check_fps(fps)
                .map_err(|m| this.format_err(this.line_no, format!("invalid scene header: {m}")))?;
        }
        this.phases = header
            .scene
            .cameras
            .iter()
            .map(|c| CameraPhase::new(c.offset_ms))
            .collect();
        this.scene = header.scene;
        this.fps = header.fps;
        Ok(Start::Reader(Box::new(this)))
    }

    /// The scene declared by the header.
    pub fn scene(&self) -> &SceneSpec {
        &self.scene
    }

    /// The frame rate declared by the header, if any.
    pub fn fps(&self) -> Option<f64> {
        self.fps
    }

    /// Switches off duplicate-batch detection, which keeps one small bitset per frame id
    /// seen; for unbounded streams whose memory must stay flat.
    pub fn without_duplicate_check(mut self) -> Self {
        self.seen = None;
        self
    }

    /// Skips broken boxes and lines (with a count) instead of failing on the first.
    pub(crate) fn lenient(mut self) -> Self {
        self.lenient = true;
        self
    }

    /// Boxes clipped and boxes and lines skipped so far.
    pub fn stats(&self) -> &ReadStats {
        &self.stats
    }

    /// The 1-based number of the last line read.
    pub fn line(&self) -> usize {
        self.line_no
    }

    pub(super) fn empty_error(source_name: String) -> Error {
        Error::Format {
            source_name,
            line: 1,
            message: "empty recording: missing the scene header line {\"scene\": {...}}".into(),
        }
    }

    pub(super) fn format_err(&self, line: usize, message: impl Into<String>) -> Error {
        Error::Format {
            source_name: self.source_name.clone(),
            line,
            message: message.into(),
        }
    }

    /// The next non-blank line (trimmed), or `None` at end of input; `Some(Err)` for a line
    /// that is not UTF-8.
    fn next_line(&mut self) -> Result<Option<Result<String>>> {
        loop {
            self.buf.clear();
            let n = self
                .reader
                .read_until(b'\n', &mut self.buf)
                .map_err(|e| Error::io(&self.source_name, e))?;
            if n == 0 {
                return Ok(None);
            }
            self.line_no += 1;
            self.unterminated = self.buf.last() != Some(&b'\n');
            self.not_json = false;
            let Ok(text) = std::str::from_utf8(&self.buf) else {
                self.not_json = true;
                return Ok(Some(Err(
                    self.format_err(self.line_no, "malformed batch: not UTF-8")
                )));
            };
            let trimmed = text.trim();
            if !trimmed.is_empty() {
                return Ok(Some(Ok(trimmed.to_string())));
            }
        }
    }

    /// Parses and validates one batch line.
    fn parse_batch(&mut self, line: &str) -> Result<Batch> {
        let mut batch: Batch = serde_json::from_str(line).map_err(|e| {
            self.not_json = e.is_syntax() || e.is_eof();
            let message = if line.contains("\"scene\"") {
                format!("unexpected second scene header or malformed batch: {e}")
            } else {
                format!("malformed batch: {e}")
            };
            self.format_err(self.line_no, message)
        })?;
        let cam = self.scene.camera_index(&batch.camera).map_err(|_| {
            self.format_err(
                self.line_no,
                format!(
                    "unknown camera '{}' (scene '{}' has {})",
                    batch.camera,
                    self.scene.name,
                    camera_list(&self.scene)
                ),
            )
        })?;
        if batch.frame_id == 0
            && let Some(time) = batch.time
        {
            batch.frame_id = self.tick_of(cam, time)?;
        }
        let words = self.scene.cameras.len().div_ceil(64);
        let first_report = self.seen.as_mut().is_none_or(|seen| {
            let bits = seen
                .entry(batch.frame_id)
                .or_insert_with(|| vec![0u64; words].into_boxed_slice());
            let (word, bit) = (cam / 64, 1u64 << (cam % 64));
            let fresh = bits[word] & bit == 0;
            bits[word] |= bit;
            fresh
        });
        if !first_report {
            return Err(self.format_err(
                self.line_no,
                format!(
                    "duplicate batch: camera '{}' already reported frame {}",
                    batch.camera, batch.frame_id
                ),
            ));
        }
        let camera = &self.scene.cameras[cam];
        let mut kept = Vec::with_capacity(batch.detections.len());
        for (i, mut det) in std::mem::take(&mut batch.detections)
            .into_iter()
            .enumerate()
        {
            match self.appearance.check(i, &mut det, camera) {
                Ok(clipped) => {
                    self.stats.clipped_boxes += usize::from(clipped);
                    kept.push(det);
                }
                Err(e) => {
                    let e = self.format_err(
                        self.line_no,
                        format!("camera '{}' frame {}: {e}", batch.camera, batch.frame_id),
                    );
                    if !self.lenient {
                        return Err(e);
                    }
                    self.stats.skipped_boxes += 1;
                    self.stats.skipped(&e);
                }
            }
        }
        batch.detections = kept;
        Ok(batch)
    }
}

impl<R: BufRead> RecordingReader<R> {
    /// The camera's own frame id of a batch that gives only its capture time: the tick of
    /// the header's `fps` nearest the time less the camera's clock offset in ms, declared
    /// (`offset_ms`) or followed from its times as the server follows it
    /// ([`crossview_core::capture::CameraPhase`]); its whole-frame `offset` is applied when
    /// frames are assembled, as for any batch.
    fn tick_of(&mut self, cam: usize, time: CaptureTime) -> Result<u64> {
        let camera = &self.scene.cameras[cam];
        let Some(ticks) = self.fps.and_then(|f| Ticks::new(f).ok()) else {
            return Err(self.format_err(
                self.line_no,
                format!(
                    "camera '{}' gives a capture time and no frame_id: the header must declare \
                     the frame rate (\"fps\") its times are grouped at",
                    camera.name
                ),
            ));
        };
        let Some(placed) = self.phases[cam].place(&ticks, time) else {
            return Err(self.format_err(
                self.line_no,
                format!(
                    "camera '{}' time {time} less its clock offset is before 1970",
                    camera.name
                ),
            ));
        };
        self.phases[cam].accept(&placed);
        Ok(placed.tick)
    }
}

pub(super) fn camera_list(scene: &SceneSpec) -> String {
    scene
        .cameras
        .iter()
        .map(|c| c.name.as_str())
        .collect::<Vec<_>>()
        .join(", ")
}

impl<R: BufRead> Iterator for RecordingReader<R> {
    type Item = Result<Batch>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        loop {
            let result = match self.next_line() {
                Ok(None) => {
                    self.done = true;
                    return None;
                }
                Ok(Some(line)) => match line.and_then(|l| self.parse_batch(&l)) {
                    // The input's last line, cut short: torn by a crash, dropped and counted.
                    Err(_) if self.unterminated && self.not_json => {
                        self.stats.torn_lines += 1;
                        tracing::debug!(source = %self.source_name, line = self.line_no, "dropped a torn last line");
                        self.done = true;
                        return None;
                    }
                    Err(e @ Error::Format { .. }) if self.lenient => {
                        self.stats.skipped_lines += 1;
                        self.stats.skipped(&e);
                        continue;
                    }
                    r => r,
                },
                Err(e) => Err(e),
            };
            if result.is_err() {
                self.done = true;
            }
            return Some(result);
        }
    }
}
