//! An identity's confidence, from label-free quantities only: the geometric mean of
//! - cohesion: the mean confidence `max(S, P)` over its member pairs (1 for one box);
//! - completeness: `∏ (1 − c)` over the other cameras with boxes, `c` the best confidence of
//!   a member's Hungarian partner there (the chance that no box of that person was left out);
//! - coverage: the share of the frame's cameras with boxes that it spans (a box alone among
//!   many cameras is rarely a person only one camera sees).
//!
//! Chosen on the WILDTRACK training frames and the simulator presets (precision by decile
//! monotone there; BENCHMARKS.md, "Identities").
use super::evidence::{Evidence, NONE};

/// The confidence of the identity made of boxes `members` (sorted, one per camera), in [0, 1].
pub(super) fn confidence(ev: &Evidence, members: &[usize]) -> f32 {
    let c = ev.cameras;
    let (mut sum, mut pairs) = (0f32, 0u32);
    for (i, &u) in members.iter().enumerate() {
        for &v in &members[i + 1..] {
            sum += ev.link_confidence(u, v).clamp(0.0, 1.0);
            pairs += 1;
        }
    }
    let cohesion = if pairs == 0 { 1.0 } else { sum / pairs as f32 };
    let mut complete = 1f32;
    let mut with_boxes = 0usize;
    for cam in 0..c {
        if ev.offsets[cam + 1] == ev.offsets[cam] {
            continue;
        }
        with_boxes += 1;
        if members.iter().any(|&u| ev.cam_of[u] == cam) {
            continue;
        }
        let best = members
            .iter()
            .filter(|&&u| ev.partner[u * c + cam] != NONE)
            .map(|&u| ev.conf[u * c + cam].clamp(0.0, 1.0))
            .fold(0f32, f32::max);
        complete *= 1.0 - best;
    }
    let coverage = members.len() as f32 / with_boxes.max(1) as f32;
    (cohesion * complete * coverage).cbrt().clamp(0.0, 1.0)
}
