//! Whole recordings from files, stdin and directories, several read as one.
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};

use crossview_core::SceneSpec;
use crossview_core::{Error, Result};

use super::Recording;
use super::assemble::{FrameAssembler, Inserted};
use super::reader::{AppearanceLen, ReadStats, RecordingReader, Start, camera_list};

/// Reads a whole recording from `path` into memory, frames sorted by id; fails on the first
/// broken box or line. `path` is a file, `-` (stdin) or a directory (every `*.jsonl` below
/// it, see the module docs).
pub fn read_recording(path: impl AsRef<Path>) -> Result<Recording> {
    read_recording_with(path, true).map(|(rec, _)| rec)
}

/// [`read_recording`], `strict` or lenient (skipping broken boxes and lines, see
/// the module docs), with what was clipped, skipped and dropped.
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
/// docs) as one recording: all must declare the same scene (each file's batches grouped by its
/// own header's clock offsets); torn last lines are dropped and counted in
/// [`ReadStats::torn_lines`]. `strict` as in [`read_recording_with`].
pub fn read_recordings(paths: &[impl AsRef<Path>], strict: bool) -> Result<(Recording, ReadStats)> {
    let files = recording_files(paths)?;
    let several = files.len() > 1 || paths.iter().any(|p| p.as_ref().is_dir());
    let mut stats = ReadStats::default();
    // The first file's scene and frame rate, which every other file must repeat, and its name.
    let mut first: Option<(SceneSpec, Option<f64>, String)> = None;
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
            None => first = Some((reader.scene().clone(), reader.fps(), name.clone())),
            Some((scene, _, first_name)) if !same_cameras(scene, reader.scene()) => {
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
            Some((_, fps, first_name)) if *fps != reader.fps() => {
                let shown = |r: Option<f64>| r.map_or("none".to_string(), |r| r.to_string());
                return Err(Error::Format {
                    source_name: name,
                    line: 1,
                    message: format!(
                        "frame rate {} differs from {} of {first_name}: the files of one recording must declare the same fps",
                        shown(reader.fps()),
                        shown(*fps),
                    ),
                });
            }
            Some(_) => {}
        }
        reader.appearance = appearance;
        let scene = reader.scene().clone();
        let assembler = assembler.get_or_insert_with(|| FrameAssembler::new(&scene));
        // Each file's batches by its own header's clock offsets (a server whose
        // `--auto-align` changed one started a new file with the new offsets).
        assembler.use_offsets(&scene);
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
    let (Some((scene, fps, _)), Some(assembler)) = (first, assembler) else {
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
            fps,
        },
        stats,
    ))
}

/// The same scene up to the cameras' clock offsets: name, camera names and image sizes.
fn same_cameras(a: &SceneSpec, b: &SceneSpec) -> bool {
    a.name == b.name
        && a.cameras.len() == b.cameras.len()
        && a.cameras
            .iter()
            .zip(&b.cameras)
            .all(|(x, y)| (&x.name, x.width, x.height) == (&y.name, y.width, y.height))
}
