//! The `--dump-pairs` file: one [`PairRecord`] per line (JSON Lines). With it a third party
//! can recompute every SPEC §5 metric without the model or the data.
use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter, Write};
use std::path::Path;

use crate::metrics::PairRecord;
use crate::parallel::{DEFAULT_WINDOW, map_ordered};
use crossview_core::{Error, Result};

/// Writes `records` to `out`, one JSON object per line.
pub(crate) fn write_pairs<W: Write>(mut out: W, records: &[PairRecord], dest: &str) -> Result<()> {
    for r in records {
        serde_json::to_writer(&mut out, r).map_err(|e| Error::Format {
            source_name: dest.to_string(),
            line: 0,
            message: format!("cannot encode pair record: {e}"),
        })?;
        out.write_all(b"\n").map_err(|e| Error::io(dest, e))?;
    }
    out.flush().map_err(|e| Error::io(dest, e))
}

/// Records formatted per block by one worker of [`write_dump_on`].
const DUMP_BLOCK: usize = 64;

/// [`write_dump`] with the lines formatted on `workers` threads: blocks of records are dealt
/// to them ([`map_ordered`]) and written in order, so the file is byte-identical.
pub fn write_dump_on(path: impl AsRef<Path>, records: &[PairRecord], workers: usize) -> Result<()> {
    let path = path.as_ref();
    let dest = path.display().to_string();
    let file = File::create(path).map_err(|e| Error::io(path, e))?;
    let mut out = BufWriter::new(file);
    let blocks: Vec<&[PairRecord]> = records.chunks(DUMP_BLOCK).collect();
    let mut threads = vec![(); workers.max(1)];
    map_ordered(
        &blocks,
        &mut threads,
        DEFAULT_WINDOW,
        |_, _, block| {
            let mut buf = Vec::new();
            write_pairs(&mut buf, block, &dest)?;
            Ok(buf)
        },
        |_, buf| out.write_all(&buf).map_err(|e| Error::io(path, e)),
    )?;
    out.flush().map_err(|e| Error::io(path, e))
}

/// Reads pair records from `input`; `source` names it in errors. Blank lines are skipped;
/// a malformed or inconsistent line is an [`Error::Format`] with its 1-based line number.
pub(crate) fn read_pairs<R: BufRead>(input: R, source: &str) -> Result<Vec<PairRecord>> {
    let mut out = Vec::new();
    for (k, line) in input.lines().enumerate() {
        let line = line.map_err(|e| Error::io(source, e))?;
        if line.trim().is_empty() {
            continue;
        }
        let fmt = |message: String| Error::Format {
            source_name: source.to_string(),
            line: k + 1,
            message,
        };
        let rec: PairRecord =
            serde_json::from_str(&line).map_err(|e| fmt(format!("not a pair record: {e}")))?;
        rec.validate().map_err(|e| fmt(e.to_string()))?;
        out.push(rec);
    }
    Ok(out)
}

/// Reads a dump file written by [`write_dump`].
pub fn read_dump(path: impl AsRef<Path>) -> Result<Vec<PairRecord>> {
    let path = path.as_ref();
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    read_pairs(BufReader::new(file), &path.display().to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_line_numbers_in_errors() {
        let r = PairRecord {
            frame_id: 5,
            camera_a: "C1".into(),
            camera_b: "C2".into(),
            ids_a: vec![1, 2],
            ids_b: vec![2],
            scores: vec![0.25, 0.75],
            matches: vec![(1, 0, 0.75)],
            identity_matches: Some(vec![(1, 0, 0.75)]),
        };
        let mut buf = Vec::new();
        write_pairs(&mut buf, &[r.clone(), r.clone()], "mem").unwrap();
        let back = read_pairs(&buf[..], "mem").unwrap();
        assert_eq!(back, vec![r.clone(), r]);
        let bad = b"\n{\"frame_id\":1}\n";
        let err = read_pairs(&bad[..], "dump.jsonl").unwrap_err().to_string();
        assert!(err.starts_with("dump.jsonl:2:"), "{err}");
        let inconsistent = br#"{"frame_id":1,"camera_a":"a","camera_b":"b","ids_a":[1],"ids_b":[1],"scores":[0.5,0.5],"matches":[]}"#;
        let err = read_pairs(&inconsistent[..], "d").unwrap_err().to_string();
        assert!(err.contains("scores"), "{err}");
    }

    #[test]
    fn a_dump_written_by_several_threads_is_the_same_file() {
        let records: Vec<PairRecord> = (0..300u64)
            .map(|f| PairRecord {
                frame_id: f,
                camera_a: "C1".into(),
                camera_b: "C2".into(),
                ids_a: vec![f, 1],
                ids_b: vec![1],
                scores: vec![f as f32 / 300.0, 0.5],
                matches: vec![(1, 0, 0.5)],
                identity_matches: None,
            })
            .collect();
        let dir = tempfile::tempdir().unwrap();
        let (one, three) = (dir.path().join("1.jsonl"), dir.path().join("3.jsonl"));
        write_dump_on(&one, &records, 1).unwrap();
        write_dump_on(&three, &records, 3).unwrap();
        let bytes = std::fs::read(&one).unwrap();
        assert_eq!(bytes, std::fs::read(&three).unwrap());
        assert_eq!(read_dump(&three).unwrap(), records);
    }
}
