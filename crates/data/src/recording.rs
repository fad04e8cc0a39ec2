//! The SPEC §7 JSONL recording: a scene header line, then one camera batch per line.
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
//! ([`Detection::clip_to_image`], the one rule shared with the server) and counted in
//! [`ReadStats::clipped_boxes`]. A [`lenient`](RecordingReader::lenient) reader (the trainer's
//! default) skips a broken box or a broken line with a count instead of failing: real
//! detector output is careless, and one bad box must not abort a 71,000-box recording.
//!
//! **Several files, directories, torn tails.** A recording may span several files (as
//! `crossview serve --record` writes them, rotated): [`read_recordings`] takes files and
//! directories — a directory stands for every `*.jsonl` file below it, recursively (symbolic
//! links to directories are not followed), in path order (the server's file names sort by
//! start time) — and reads them, in the order given, as one recording. Every file starts with
//! its own scene header and all must declare the same scene; a frame may be spread over several
//! files (a rotation between its cameras' batches), but a camera twice for one frame, in one
//! file or two, is still a duplicate. The **last line of each file**, when it has no newline at
//! its end and is not complete JSON (a crash cut it short while it was written), is **torn**:
//! it is dropped and counted ([`ReadStats::torn_lines`], one `warn` log with the count), never
//! an error; a file that holds nothing else (a torn header, or no bytes at all) adds nothing.
//! A broken line anywhere else, or a last line that ends with its newline, stays an error
//! naming its file and line.
use std::collections::{BTreeMap, HashMap, HashSet};
use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter, Read, Write};
use std::ops::RangeBounds;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crossview_core::types::{BatchLine, HeaderLine};
use crossview_core::{Batch, CameraSpec, Detection, Frame, SceneSpec};
use crossview_core::{Error, Result};

/// A whole recording in memory: the scene and its frames sorted by frame id.
/// `frames[k].views[c]` is `None` when camera `c` sent no batch for that frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Recording {
    pub scene: SceneSpec,
    pub frames: Vec<Frame>,
}

/// The first line of a recording: `{"scene": {...}}`.
#[derive(Debug, Serialize, Deserialize)]
struct Header {
    scene: SceneSpec,
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

/// Tracks the appearance-vector length of a scene: fixed by the first vector seen.
#[derive(Debug, Default, Clone, Copy)]
struct AppearanceLen(Option<usize>);

impl AppearanceLen {
    /// Validates one detection (field `detections[i]...`), checks that all appearance vectors
    /// share one length and clips the box to `cam`'s image; returns whether it was clipped.
    fn check(&mut self, i: usize, det: &mut Detection, cam: &CameraSpec) -> Result<bool> {
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
    fn skipped(&mut self, problem: &Error) {
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
/// [`lenient`](Self::lenient) reader skips broken boxes and lines instead (counted in
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
    appearance: AppearanceLen,
    /// Per frame id, a bitset of the cameras that reported it (duplicate detection);
    /// `None` when the check is switched off.
    seen: Option<HashMap<u64, Box<[u64]>>>,
    done: bool,
    lenient: bool,
    stats: ReadStats,
}

/// What the start of an input holds.
enum Start<R> {
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
    fn start(reader: R, source_name: String) -> Result<Start<R>> {
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
                        "invalid scene header (expected {{\"scene\": {{\"name\", \"cameras\"}}}}): {e}"
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
        this.scene = header.scene;
        Ok(Start::Reader(Box::new(this)))
    }

    /// The scene declared by the header.
    pub fn scene(&self) -> &SceneSpec {
        &self.scene
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

    fn empty_error(source_name: String) -> Error {
        Error::Format {
            source_name,
            line: 1,
            message: "empty recording: missing the scene header line {\"scene\": {...}}".into(),
        }
    }

    fn format_err(&self, line: usize, message: impl Into<String>) -> Error {
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

fn camera_list(scene: &SceneSpec) -> String {
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

/// Reads a whole recording from `path` into memory, frames sorted by id; fails on the first
/// broken box or line. `path` is a file, `-` (stdin) or a directory (every `*.jsonl` below
/// it, see the module docs).
pub fn read_recording(path: impl AsRef<Path>) -> Result<Recording> {
    read_recording_with(path, true).map(|(rec, _)| rec)
}

/// [`read_recording`], `strict` or lenient (skipping broken boxes and lines, see
/// [`RecordingReader::lenient`]), with what was clipped, skipped and dropped.
pub fn read_recording_with(path: impl AsRef<Path>, strict: bool) -> Result<(Recording, ReadStats)> {
    read_recordings(&[path.as_ref()], strict)
}

/// The recording files `paths` stand for, in reading order: a file (or `-`) itself, a
/// directory every `*.jsonl` file below it, recursively, sorted by path. A directory without
/// one is an error.
pub fn recording_files(paths: &[impl AsRef<Path>]) -> Result<Vec<PathBuf>> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
        let mut entries: Vec<_> = std::fs::read_dir(dir)
            .map_err(|e| Error::io(dir, e))?
            .collect::<std::io::Result<_>>()
            .map_err(|e| Error::io(dir, e))?;
        entries.sort_by_key(|e| e.file_name());
        for entry in entries {
            let path = entry.path();
            let kind = entry.file_type().map_err(|e| Error::io(&path, e))?;
            if kind.is_dir() {
                walk(&path, out)?;
            } else if path.extension().is_some_and(|x| x == "jsonl") && path.is_file() {
                out.push(path);
            }
        }
        Ok(())
    }
    let mut files = Vec::new();
    for p in paths {
        let p = p.as_ref();
        if p != Path::new("-") && p.is_dir() {
            let before = files.len();
            walk(p, &mut files)?;
            if files.len() == before {
                return Err(Error::Format {
                    source_name: p.display().to_string(),
                    line: 0,
                    message: "no recording (*.jsonl) files in this directory".into(),
                });
            }
        } else {
            files.push(p.to_path_buf());
        }
    }
    Ok(files)
}

/// Reads the recording files and directories `paths` (see [`recording_files`] and the module
/// docs) as one recording: all must declare the same scene; torn last lines are dropped and
/// counted in [`ReadStats::torn_lines`]. `strict` as in [`read_recording_with`].
pub fn read_recordings(paths: &[impl AsRef<Path>], strict: bool) -> Result<(Recording, ReadStats)> {
    let files = recording_files(paths)?;
    let several = files.len() > 1 || paths.iter().any(|p| p.as_ref().is_dir());
    let mut stats = ReadStats::default();
    let mut first: Option<(SceneSpec, String)> = None;
    let mut appearance = AppearanceLen::default();
    let mut assembler: Option<FrameAssembler> = None;
    let mut last_problem: Option<Error> = None;
    for path in &files {
        let name = path.display().to_string();
        let inner: Box<dyn Read> = if path == Path::new("-") {
            Box::new(std::io::stdin())
        } else {
            Box::new(File::open(path).map_err(|e| Error::io(path, e))?)
        };
        let mut reader = match RecordingReader::start(BufReader::new(inner), name.clone())? {
            Start::Reader(r) => *r,
            Start::Empty(n) => {
                if !several {
                    return Err(RecordingReader::<&[u8]>::empty_error(n));
                }
                stats.empty_files += 1;
                tracing::debug!(file = %name, "skipped an empty recording file");
                continue;
            }
            Start::TornHeader(e) => {
                stats.torn_lines += 1;
                last_problem = Some(e);
                continue;
            }
        };
        if !strict {
            reader = reader.lenient();
        }
        match &first {
            None => first = Some((reader.scene().clone(), name.clone())),
            Some((scene, first_name)) if scene != reader.scene() => {
                return Err(Error::Format {
                    source_name: name,
                    line: 1,
                    message: format!(
                        "scene '{}' ({}) differs from scene '{}' ({}) of {first_name}: the files of one recording must declare the same scene",
                        reader.scene().name,
                        camera_list(reader.scene()),
                        scene.name,
                        camera_list(scene)
                    ),
                });
            }
            Some(_) => {}
        }
        reader.appearance = appearance;
        let scene = reader.scene().clone();
        let assembler = assembler.get_or_insert_with(|| FrameAssembler::new(&scene));
        while let Some(batch) = reader.next() {
            let batch = batch?;
            let cam = scene.camera_index(&batch.camera)?;
            let frame_id = batch.frame_id;
            let inserted = assembler.insert(cam, frame_id, batch.detections);
            if inserted != Inserted::Added {
                // A duplicate across files (the reader finds those within one file).
                let e = reader.format_err(
                    reader.line(),
                    match inserted {
                        Inserted::OutOfRange => format!(
                            "camera '{}' frame {frame_id} less the camera's clock offset is out of range",
                            batch.camera
                        ),
                        _ => format!(
                            "duplicate batch: camera '{}' already reported frame {frame_id} in an earlier file",
                            batch.camera
                        ),
                    },
                );
                if strict {
                    return Err(e);
                }
                reader.stats.skipped_lines += 1;
                reader.stats.skipped(&e);
            }
        }
        appearance = reader.appearance;
        let s = reader.stats;
        stats.clipped_boxes += s.clipped_boxes;
        stats.skipped_boxes += s.skipped_boxes;
        stats.skipped_lines += s.skipped_lines;
        stats.torn_lines += s.torn_lines;
        if stats.first_problem.is_none() {
            stats.first_problem = s.first_problem;
        }
    }
    let (Some((scene, _)), Some(assembler)) = (first, assembler) else {
        return Err(last_problem.unwrap_or_else(|| {
            RecordingReader::<&[u8]>::empty_error(
                files
                    .first()
                    .map(|p| p.display().to_string())
                    .unwrap_or_default(),
            )
        }));
    };
    if stats.torn_lines > 0 {
        tracing::warn!(
            torn_lines = stats.torn_lines,
            files = files.len(),
            "dropped torn last lines (cut short by a crash while they were written)"
        );
    }
    Ok((
        Recording {
            frames: assembler.finish(),
            scene,
        },
        stats,
    ))
}

/// Collects batches into frames keyed (and so sorted) by frame id: a camera's batch `N`
/// goes to frame `N − offset` (its clock offset, [`CameraSpec::frame_of`]).
struct FrameAssembler {
    cameras: Vec<CameraSpec>,
    frames: BTreeMap<u64, Frame>,
}

/// What [`FrameAssembler::insert`] made of a batch.
#[derive(Debug, PartialEq, Eq)]
enum Inserted {
    Added,
    /// The camera had already reported the frame.
    Duplicate,
    /// The frame id less the camera's offset falls outside `0..=u64::MAX`.
    OutOfRange,
}

impl FrameAssembler {
    fn new(scene: &SceneSpec) -> Self {
        FrameAssembler {
            cameras: scene.cameras.clone(),
            frames: BTreeMap::new(),
        }
    }

    /// Stores camera `cam`'s detections of its frame id `frame_id`.
    fn insert(&mut self, cam: usize, frame_id: u64, detections: Vec<Detection>) -> Inserted {
        let n = self.cameras.len();
        let Some(frame_id) = self.cameras[cam].frame_of(frame_id) else {
            return Inserted::OutOfRange;
        };
        let frame = self
            .frames
            .entry(frame_id)
            .or_insert_with(|| Frame::new(frame_id, n));
        if frame.views[cam].is_some() {
            return Inserted::Duplicate;
        }
        frame.views[cam] = Some(detections);
        Inserted::Added
    }

    fn finish(self) -> Vec<Frame> {
        self.frames.into_values().collect()
    }
}

impl Recording {
    /// Assembles frames from batches in any order: frames sorted by frame id, `views[c]` is
    /// `None` where camera `c` sent nothing. Fails on an invalid scene, an unknown camera
    /// ([`Error::UnknownCamera`]), a second batch for the same camera and frame
    /// ([`Error::DuplicateBatch`]) or an invalid detection / inconsistent appearance length
    /// ([`Error::InvalidArgument`], field `<camera>@<frame>.detections[i]...`). Boxes
    /// overlapping the image edge are clipped ([`Detection::clip_to_image`]).
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
                        detections: dets.clone(),
                    }
                })
            })
        })
    }
}

/// Writes a recording: the header on creation, then batch lines; buffered. Call
/// [`RecordingWriter::finish`] to flush and surface write errors.
pub struct RecordingWriter<W: Write> {
    dest_name: String,
    writer: BufWriter<W>,
    scene: SceneSpec,
}

impl RecordingWriter<Box<dyn Write>> {
    /// Creates (truncates) `path` (`-` = stdout) and writes the header.
    pub fn create(path: impl AsRef<Path>, scene: &SceneSpec) -> Result<Self> {
        let path = path.as_ref();
        let inner: Box<dyn Write> = if path == Path::new("-") {
            Box::new(std::io::stdout())
        } else {
            Box::new(File::create(path).map_err(|e| Error::io(path, e))?)
        };
        RecordingWriter::new(inner, path.display().to_string(), scene)
    }
}

impl<W: Write> RecordingWriter<W> {
    /// Wraps a writer (`dest_name` names it in errors) and writes the header line.
    pub fn new(writer: W, dest_name: impl Into<String>, scene: &SceneSpec) -> Result<Self> {
        validate_scene(scene).map_err(|m| Error::invalid("scene", m))?;
        let mut this = RecordingWriter {
            dest_name: dest_name.into(),
            writer: BufWriter::new(writer),
            scene: scene.clone(),
        };
        this.write_json(&HeaderLine { scene })?;
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
    let mut writer = RecordingWriter::create(path, &recording.scene)?;
    for frame in &recording.frames {
        writer.write_frame(frame)?;
    }
    writer.finish()?;
    Ok(())
}
