//! The chronological train / validation / test split of SPEC §6.
//!
//! Over `n` frames in time order: test = the last 10% of frames, validation = the last 20% of
//! the rest, training = the remainder. Rounding: both sizes are rounded *up*
//! (`n_test = ceil(n / 10)`, `n_val = ceil((n - n_test) / 5)`), so any non-empty sequence has a
//! test frame, and exact multiples are unaffected. For WILDTRACK's 400 frames (0..=1995 step 5)
//! that is 40 test frames (1800..=1995), 72 validation frames (1440..=1795) and 288 training
//! frames (0..=1435).
use std::fmt;
use std::ops::Range;
use std::str::FromStr;

use crossview_core::{Error, Result};

/// One part of the chronological split.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Part {
    /// The first ~72% of frames.
    Train,
    /// The ~18% of frames before the test part.
    Val,
    /// The last ~10% of frames.
    Test,
}

impl Part {
    /// The lower-case name used on the command line (`train`, `val`, `test`).
    pub fn as_str(self) -> &'static str {
        match self {
            Part::Train => "train",
            Part::Val => "val",
            Part::Test => "test",
        }
    }
}

impl fmt::Display for Part {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for Part {
    type Err = Error;

    fn from_str(s: &str) -> Result<Self> {
        match s {
            "train" | "training" => Ok(Part::Train),
            "val" | "validation" => Ok(Part::Val),
            "test" => Ok(Part::Test),
            other => Err(Error::invalid(
                "part",
                format!("expected train, val or test, got '{other}'"),
            )),
        }
    }
}

/// Index ranges of the three parts over a sequence of `n` frames (contiguous, in order).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct SplitRanges {
    pub train: Range<usize>,
    pub val: Range<usize>,
    pub test: Range<usize>,
}

impl SplitRanges {
    /// The index range of `part`.
    pub fn get(&self, part: Part) -> Range<usize> {
        match part {
            Part::Train => self.train.clone(),
            Part::Val => self.val.clone(),
            Part::Test => self.test.clone(),
        }
    }
}

/// The split of `n` frames (see the module doc for the rounding).
pub(crate) fn split_ranges(n: usize) -> SplitRanges {
    let n_test = n.div_ceil(10);
    let rest = n - n_test;
    let n_val = rest.div_ceil(5);
    let n_train = rest - n_val;
    SplitRanges {
        train: 0..n_train,
        val: n_train..rest,
        test: rest..n,
    }
}

/// The frame ids of `part` of a sorted sequence. `frame_ids` must be strictly increasing
/// ([`Error::InvalidArgument`] otherwise).
pub fn split_frames(frame_ids: &[u64], part: Part) -> Result<&[u64]> {
    if let Some(w) = frame_ids.windows(2).find(|w| w[0] >= w[1]) {
        return Err(Error::invalid(
            "frame_ids",
            format!("must be strictly increasing, found {} then {}", w[0], w[1]),
        ));
    }
    Ok(&frame_ids[split_ranges(frame_ids.len()).get(part)])
}

/// The inclusive frame-id bounds `(first, last)` of `part` of a sorted sequence, or `None`
/// when that part is empty.
pub fn split_bounds(frame_ids: &[u64], part: Part) -> Result<Option<(u64, u64)>> {
    let ids = split_frames(frame_ids, part)?;
    Ok(ids.first().zip(ids.last()).map(|(a, b)| (*a, *b)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_partition_the_sequence() {
        for n in 0..500 {
            let r = split_ranges(n);
            assert_eq!(r.train.start, 0);
            assert_eq!(r.train.end, r.val.start);
            assert_eq!(r.val.end, r.test.start);
            assert_eq!(r.test.end, n);
            if n > 0 {
                assert!(!r.test.is_empty());
            }
        }
        let r = split_ranges(400);
        assert_eq!((r.train.len(), r.val.len(), r.test.len()), (288, 72, 40));
        let r = split_ranges(7);
        assert_eq!((r.train.len(), r.val.len(), r.test.len()), (4, 2, 1));
    }

    #[test]
    fn unsorted_ids_are_rejected() {
        assert!(split_frames(&[0, 5, 5], Part::Train).is_err());
        assert!(split_frames(&[5, 0], Part::Train).is_err());
        assert_eq!(split_frames(&[], Part::Test).unwrap(), &[] as &[u64]);
        assert_eq!(split_bounds(&[], Part::Val).unwrap(), None);
    }

    #[test]
    fn parts_parse() {
        assert_eq!("val".parse::<Part>().unwrap(), Part::Val);
        assert_eq!("training".parse::<Part>().unwrap(), Part::Train);
        assert!("dev".parse::<Part>().is_err());
    }
}
