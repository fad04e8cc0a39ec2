//! The `--dump-pairs` file: one [`PairRecord`] per line (JSON Lines). With it a third party
//! can recompute every SPEC §5 metric without the model or the data.
use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter, Write};
use std::path::Path;

use crate::eval::metrics::PairRecord;
use crate::{Error, Result};

/// Writes `records` to `out`, one JSON object per line.
pub fn write_pairs<W: Write>(mut out: W, records: &[PairRecord], dest: &str) -> Result<()> {
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

/// Writes `records` to the file at `path` (created or truncated).
pub fn write_dump(path: impl AsRef<Path>, records: &[PairRecord]) -> Result<()> {
    let path = path.as_ref();
    let file = File::create(path).map_err(|e| Error::io(path, e))?;
    write_pairs(BufWriter::new(file), records, &path.display().to_string())
}

/// Reads pair records from `input`; `source` names it in errors. Blank lines are skipped;
/// a malformed or inconsistent line is an [`Error::Format`] with its 1-based line number.
pub fn read_pairs<R: BufRead>(input: R, source: &str) -> Result<Vec<PairRecord>> {
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
}
