//! **[ours]** Track ids that stay with a person across frames and cameras: a tracker per
//! scene, fed with each frame's identities in frame order.
//!
//! Cue: the encoder maps a box to a view-invariant geometric code (in effect a learned
//! ground-plane position), so an identity's mean embedding — the centroid of its members'
//! embeddings — moves smoothly from frame to frame whichever cameras see it. Each frame, the
//! live tracks and the frame's identities are matched by one Hungarian assignment on the
//! distance between a track's last centroid and an identity's centroid, gated relative to the
//! frame's own scale (the median distance between its identities' centroids), so the gate
//! does not depend on the model's embedding units. A track's centroid moves towards its new
//! identity's by the identity's share of the views times its confidence, so one doubtful
//! identity (two people merged for a frame) barely moves it. A second cue comes from the
//! images: the mean overlap (IoU) of an identity's boxes with the track's boxes in the cameras
//! both see, each track box moved on by its own smoothed motion in that camera (at 2 frames/s
//! a walking person's box rarely overlaps its last position, but overlaps its predicted one),
//! is taken off the relative distance.
//!
//! Bounded state: a track unseen for `max_age` frames is retired, and at most `max_tracks`
//! live at once (the longest unseen go first). Ages count the frames given to
//! [`Tracker::update`], not frame ids, so a gap in the ids, a restart of the ids (a scene whose
//! cameras restarted) or a partial frame neither resets nor ages the tracks by itself.
use std::borrow::Cow;

use ndarray::Array2;

use crate::distances::euclidean_distances;
use crate::embeddings::FrameEmbeddings;
use crate::identity::Identity;
use crate::lsa;
use crate::motion::{MovingBox, iou};
use crate::types::Frame;

/// How identities are linked over time.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackerConfig {
    /// An identity continues a track only when their centroids are closer than `gate` times
    /// the frame's median distance between identity centroids.
    pub gate: f32,
    /// Frames a track survives without an identity before it is retired.
    pub max_age: u32,
    /// Most live tracks per scene (memory bound); the longest unseen are retired first.
    pub max_tracks: usize,
    /// How fast a track's velocity follows its observed motion (0 = constant position).
    pub velocity_weight: f32,
    /// Weight of the image cue: the mean overlap (IoU), over the cameras both see, of an
    /// identity's boxes with the track's predicted boxes, taken off the relative distance.
    pub iou_weight: f32,
    /// How fast a track's box velocity in each camera follows the box's observed motion
    /// (0 = the last box is the prediction).
    pub box_velocity_weight: f32,
}

impl Default for TrackerConfig {
    fn default() -> Self {
        // Chosen on the WILDTRACK training frames' ground truth (0..1435, 2 frames/s;
        // BENCHMARKS.md, "Tracking"), not on validation.
        TrackerConfig {
            gate: 0.5,
            max_age: 5,
            max_tracks: 4096,
            velocity_weight: 0.8,
            iou_weight: 2.0,
            box_velocity_weight: 0.7,
        }
    }
}

#[derive(Debug, Clone)]
struct Track {
    id: u64,
    centroid: Vec<f32>,
    /// Centroid change per frame (smoothed).
    velocity: Vec<f32>,
    /// The track's box in each camera, for the image cue.
    boxes: Vec<Option<MovingBox>>,
    /// Frames since the track was last matched (0 = this frame).
    unseen: u32,
}

impl Track {
    /// The boxes expected this frame, per camera.
    fn predicted_boxes(&self) -> Vec<Option<[f32; 4]>> {
        self.boxes
            .iter()
            .map(|b| b.as_ref().map(MovingBox::predicted))
            .collect()
    }

    /// Where the track is expected this frame: its centroid moved on by its velocity.
    fn predicted(&self) -> Vec<f32> {
        let mut out = Vec::with_capacity(self.centroid.len());
        self.predict_into(&mut out);
        out
    }

    /// [`Track::predicted`], appended to `out`.
    fn predict_into(&self, out: &mut Vec<f32>) {
        let k = (self.unseen + 1) as f32;
        let moved = self.centroid.iter().zip(&self.velocity);
        out.extend(moved.map(|(c, v)| c + k * v));
    }
}

/// The tracker of one scene (see the module docs).
#[derive(Debug, Clone)]
pub struct Tracker {
    cfg: TrackerConfig,
    tracks: Vec<Track>,
    next_id: u64,
    /// The last frame's scale (median distance between its identities), for frames with
    /// fewer than two identities.
    scale: f32,
}

impl Tracker {
    /// An empty tracker.
    pub fn new(cfg: TrackerConfig) -> Self {
        Tracker {
            cfg,
            tracks: Vec::new(),
            next_id: 0,
            scale: f32::INFINITY,
        }
    }

    /// Ends every track (the embedding space changed: a new model); ids go on counting from
    /// where they were, so no id is ever reused.
    pub fn end_tracks(&mut self) {
        self.tracks.clear();
        self.scale = f32::INFINITY;
    }

    /// Live tracks (matched within the last `max_age` frames).
    pub fn live_tracks(&self) -> usize {
        self.tracks.len()
    }

    /// Links the identities of `frame` (with its `embeddings`) to the live tracks and
    /// returns one track id per identity, in order. New people get new ids; tracks left
    /// unmatched age and retire after `max_age` frames.
    pub fn update(
        &mut self,
        frame: &Frame,
        identities: &[Identity],
        embeddings: &FrameEmbeddings,
    ) -> Vec<u64> {
        let centroids: Vec<Option<Vec<f32>>> = identities
            .iter()
            .map(|id| centroid(id, embeddings))
            .collect();
        let scale = median_distance(&centroids);
        if scale.is_finite() && scale > 0.0 {
            self.scale = scale;
        }
        // Tracks of another embedding width (another model) cannot continue.
        self.tracks.retain(|t| t.centroid.len() == embeddings.dim());
        let boxes: Vec<Vec<Option<[f32; 4]>>> = identities
            .iter()
            .map(|id| member_boxes(id, frame, embeddings.num_views()))
            .collect();
        let assigned = self.assign(&centroids, &boxes);
        for t in &mut self.tracks {
            t.unseen = t.unseen.saturating_add(1);
            for b in t.boxes.iter_mut().flatten() {
                b.unseen = b.unseen.saturating_add(1);
            }
        }
        let mut out = Vec::with_capacity(identities.len());
        for (k, ((id, c), b)) in identities.iter().zip(centroids).zip(boxes).enumerate() {
            let track = match assigned[k] {
                Some(t) => {
                    let track = &mut self.tracks[t];
                    let bw = self.cfg.box_velocity_weight;
                    for (last, new) in track.boxes.iter_mut().zip(b) {
                        match (last.as_mut(), new) {
                            (Some(last), Some(new)) => last.observe(new, bw),
                            (None, Some(new)) => *last = Some(MovingBox::new(new)),
                            _ => {}
                        }
                    }
                    if let Some(c) = c {
                        // Move towards the new centroid by its share of the cameras' views
                        // and its confidence: a doubtful identity (one that may merge two
                        // people) moves its track little.
                        let share = id.members.len() as f32 / embeddings.num_views().max(1) as f32;
                        let w = (share * id.confidence).clamp(0.2, 1.0);
                        let k = (track.unseen + 1) as f32;
                        let vw = self.cfg.velocity_weight * w;
                        let predicted = track.predicted();
                        for ((p, v), (q, e)) in track
                            .centroid
                            .iter_mut()
                            .zip(track.velocity.iter_mut())
                            .zip(c.iter().zip(&predicted))
                        {
                            let moved = *e + w * (q - *e);
                            *v += vw * ((moved - *p) / k - *v);
                            *p = moved;
                        }
                    }
                    track.unseen = 0;
                    track.id
                }
                None => {
                    let tid = self.next_id;
                    self.next_id += 1;
                    if let Some(c) = c {
                        self.tracks.push(Track {
                            id: tid,
                            boxes: b.into_iter().map(|b| b.map(MovingBox::new)).collect(),
                            velocity: vec![0.0; c.len()],
                            centroid: c,
                            unseen: 0,
                        });
                    }
                    tid
                }
            };
            out.push(track);
        }
        self.retire();
        out
    }

    /// Hungarian assignment of identities to tracks on the relative centroid distance
    /// (distance to the predicted centroid over the frame's scale) minus the image cue, pairs
    /// over the gate dropped; `result[k]` is identity `k`'s track index.
    fn assign(
        &self,
        centroids: &[Option<Vec<f32>>],
        boxes: &[Vec<Option<[f32; 4]>>],
    ) -> Vec<Option<usize>> {
        let rows: Vec<usize> = (0..centroids.len())
            .filter(|&k| centroids[k].is_some())
            .collect();
        let mut out = vec![None; centroids.len()];
        // Before any frame with two identities there is no scale: nothing to gate with.
        if rows.is_empty() || self.tracks.is_empty() || !self.scale.is_finite() {
            return out;
        }
        let dim = self.tracks[0].centroid.len();
        let ident = stack(
            rows.iter()
                .map(|&r| centroids[r].as_deref().unwrap_or_default()),
            dim,
        );
        let mut predicted = Vec::with_capacity(self.tracks.len() * dim);
        for t in &self.tracks {
            t.predict_into(&mut predicted);
        }
        let predicted = Array2::from_shape_vec((self.tracks.len(), dim), predicted)
            .expect("every track has the frame's embedding width");
        // All distances at once through the matrix-product kernel.
        let mut cost = euclidean_distances(ident.view(), predicted.view());
        let iou_weight = self.cfg.iou_weight;
        let track_boxes: Vec<Vec<Option<[f32; 4]>>> =
            self.tracks.iter().map(Track::predicted_boxes).collect();
        for ((r, t), c) in cost.indexed_iter_mut() {
            *c /= self.scale;
            // The image cue (at most `iou_weight`) only for pairs it could bring under the gate.
            if *c - iou_weight <= self.cfg.gate {
                *c -= iou_weight * mean_iou(&boxes[rows[r]], &track_boxes[t]);
            }
        }
        for (r, t) in lsa::assign(cost.view()) {
            if cost[(r, t)] <= self.cfg.gate {
                out[rows[r]] = Some(t);
            }
        }
        out
    }

    /// Drops tracks unseen for longer than `max_age`, then the longest unseen beyond
    /// `max_tracks`.
    fn retire(&mut self) {
        let max_age = self.cfg.max_age;
        self.tracks.retain(|t| t.unseen <= max_age);
        if self.tracks.len() > self.cfg.max_tracks {
            self.tracks.sort_by_key(|t| t.unseen);
            self.tracks.truncate(self.cfg.max_tracks);
        }
    }
}

/// The identity's box in each camera (pixels), `None` where it has no member.
fn member_boxes(id: &Identity, frame: &Frame, cameras: usize) -> Vec<Option<[f32; 4]>> {
    let mut out = vec![None; cameras];
    for &(c, i) in &id.members {
        if let Some(d) = frame
            .views
            .get(c)
            .and_then(Option::as_ref)
            .and_then(|v| v.get(i))
            && c < cameras
        {
            out[c] = Some(d.bbox);
        }
    }
    out
}

/// Mean IoU over the cameras where both `a` and `b` have a box (0 when none).
fn mean_iou(a: &[Option<[f32; 4]>], b: &[Option<[f32; 4]>]) -> f32 {
    let (mut sum, mut n) = (0f32, 0usize);
    for (x, y) in a.iter().zip(b) {
        if let (Some(x), Some(y)) = (x, y) {
            sum += iou(x, y);
            n += 1;
        }
    }
    if n == 0 { 0.0 } else { sum / n as f32 }
}

/// Mean embedding of an identity's members (`None` when none of them has a row).
fn centroid(id: &Identity, embeddings: &FrameEmbeddings) -> Option<Vec<f32>> {
    let mut sum = vec![0f32; embeddings.dim()];
    let mut n = 0usize;
    for &(c, i) in &id.members {
        let Some(view) = embeddings.view(c) else {
            continue;
        };
        if i >= view.nrows() {
            continue;
        }
        let row = view.row(i);
        // The rows of a frame's embeddings are contiguous: plain slices and a check without
        // an early exit, so both passes compile to vector code.
        let row = row
            .as_slice()
            .map_or_else(|| row.to_vec().into(), Cow::Borrowed);
        if !row.iter().fold(true, |ok, v| ok & v.is_finite()) {
            continue;
        }
        for (s, v) in sum.iter_mut().zip(row.iter()) {
            *s += v;
        }
        n += 1;
    }
    let per = n as f32;
    (n > 0).then(|| {
        sum.iter_mut().for_each(|s| *s /= per);
        sum
    })
}

/// `rows` (each `dim` long: centroids of the frame's embedding width) stacked into one matrix
/// by slice copies.
fn stack<'a>(rows: impl ExactSizeIterator<Item = &'a [f32]>, dim: usize) -> Array2<f32> {
    let n = rows.len();
    let mut flat = Vec::with_capacity(n * dim);
    rows.for_each(|r| flat.extend_from_slice(r));
    Array2::from_shape_vec((n, dim), flat).expect("every centroid has the frame's width")
}

/// Most centroids the frame's scale is taken from (evenly spread over the frame's
/// identities), so it costs at most ~2,000 distances however crowded the frame is.
const SCALE_SAMPLE: usize = 64;

/// Median distance between the centroids (the frame's scale; from at most [`SCALE_SAMPLE`] of
/// them, all distances at once through the matrix-product kernel); infinite with fewer than
/// two.
fn median_distance(centroids: &[Option<Vec<f32>>]) -> f32 {
    let all: Vec<&Vec<f32>> = centroids.iter().flatten().collect();
    let step = all.len().div_ceil(SCALE_SAMPLE).max(1);
    let cs: Vec<&Vec<f32>> = all.into_iter().step_by(step).collect();
    let n = cs.len();
    if n < 2 {
        return f32::INFINITY;
    }
    let dim = cs[0].len();
    let m = stack(cs.iter().map(|c| c.as_slice()), dim);
    let all = euclidean_distances(m.view(), m.view());
    let mut d = Vec::with_capacity(n * (n - 1) / 2);
    for i in 0..n {
        d.extend(all.row(i).iter().skip(i + 1).copied());
    }
    let mid = d.len() / 2;
    d.select_nth_unstable_by(mid, f32::total_cmp);
    d[mid]
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    /// A frame of 2 cameras where person `p` stands at `positions[p]` (1-d embedding), seen by
    /// both cameras in person order.
    fn frame(positions: &[f32]) -> (Vec<Identity>, FrameEmbeddings) {
        let n = positions.len();
        let view = Array2::from_shape_fn((n, 1), |(i, _)| positions[i]);
        let emb = FrameEmbeddings::from_views(&[Some(view.clone()), Some(view)]).unwrap();
        let ids = (0..n)
            .map(|p| Identity {
                id: p,
                confidence: 1.0,
                members: vec![(0, p), (1, p)],
            })
            .collect();
        (ids, emb)
    }

    #[test]
    fn ids_are_stable_while_people_walk() {
        let mut t = Tracker::new(TrackerConfig::default());
        let (ids, emb) = frame(&[0.0, 10.0, 20.0]);
        let first = t.update(&Frame::new(0, 2), &ids, &emb);
        assert_eq!(first, vec![0, 1, 2]);
        for step in 1..50 {
            let s = step as f32 * 0.3;
            let (ids, emb) = frame(&[s, 10.0 + s / 2.0, 20.0 + s]);
            assert_eq!(
                t.update(&Frame::new(0, 2), &ids, &emb),
                first,
                "step {step}"
            );
        }
        assert_eq!(t.live_tracks(), 3);
    }

    #[test]
    fn identities_in_another_order_keep_their_tracks() {
        let mut t = Tracker::new(TrackerConfig::default());
        let (ids, emb) = frame(&[0.0, 10.0, 20.0]);
        assert_eq!(t.update(&Frame::new(0, 2), &ids, &emb), vec![0, 1, 2]);
        let (ids, emb) = frame(&[20.5, 0.5, 10.5]);
        assert_eq!(t.update(&Frame::new(0, 2), &ids, &emb), vec![2, 0, 1]);
    }

    /// Two people side by side whose embeddings swap places from frame 3 on (the learned
    /// code cannot tell them apart), walking 60 px a frame in both cameras with boxes 40 px
    /// wide (no overlap with their own last box); a third person far away sets the scale.
    fn walking_pair(t: usize) -> (Frame, Vec<Identity>, FrameEmbeddings) {
        let x = 60.0 * t as f32;
        let swap = t >= 3 && t % 2 == 1;
        let pos = [
            if swap { 0.02 } else { 0.0 },
            if swap { 0.0 } else { 0.02 },
            10.0,
        ];
        let lefts = [100.0 + x, 300.0 + x, 1500.0];
        let (ids, emb) = frame(&pos);
        let mut f = Frame::new(t as u64, 2);
        for c in 0..2 {
            f.views[c] = Some(
                lefts
                    .iter()
                    .map(|&l| crate::types::Detection::new([l, 100.0, l + 40.0, 200.0]))
                    .collect(),
            );
        }
        (f, ids, emb)
    }

    #[test]
    fn box_motion_keeps_people_the_embeddings_confuse() {
        let run = |cfg: TrackerConfig| {
            let mut t = Tracker::new(cfg);
            (0..12)
                .map(|k| {
                    let (f, ids, emb) = walking_pair(k);
                    t.update(&f, &ids, &emb)
                })
                .collect::<Vec<_>>()
        };
        let tracks = run(TrackerConfig::default());
        assert!(tracks.iter().all(|t| t == &tracks[0]), "{tracks:?}");
        // Without the box motion the embeddings' swap wins: the test can fail.
        let still = run(TrackerConfig {
            box_velocity_weight: 0.0,
            ..TrackerConfig::default()
        });
        assert!(still.iter().any(|t| t != &still[0]), "{still:?}");
    }

    #[test]
    fn a_one_frame_merge_does_not_swap_ids() {
        let mut t = Tracker::new(TrackerConfig::default());
        let (ids, emb) = frame(&[0.0, 10.0, 20.0]);
        t.update(&Frame::new(0, 2), &ids, &emb);
        // Frame 2: persons 0 and 1 merged into one identity (one box per camera each side).
        let view = Array2::from_shape_fn((2, 1), |(i, _)| [0.2, 20.0][i]);
        let view1 = Array2::from_shape_fn((2, 1), |(i, _)| [10.2, 20.0][i]);
        let emb = FrameEmbeddings::from_views(&[Some(view), Some(view1)]).unwrap();
        let merged = vec![
            Identity {
                id: 0,
                confidence: 0.5,
                members: vec![(0, 0), (1, 0)],
            },
            Identity {
                id: 1,
                confidence: 1.0,
                members: vec![(0, 1), (1, 1)],
            },
        ];
        let got = t.update(&Frame::new(0, 2), &merged, &emb);
        assert_eq!(got[1], 2, "the person nobody confused keeps its id");
        // Frame 3: clean again; everyone is back on their own track.
        let (ids, emb) = frame(&[0.4, 10.4, 20.0]);
        assert_eq!(t.update(&Frame::new(0, 2), &ids, &emb), vec![0, 1, 2]);
    }

    #[test]
    fn new_people_get_new_ids_and_gone_ones_retire() {
        let cfg = TrackerConfig {
            max_age: 3,
            ..TrackerConfig::default()
        };
        let mut t = Tracker::new(cfg);
        let (ids, emb) = frame(&[0.0, 10.0]);
        assert_eq!(t.update(&Frame::new(0, 2), &ids, &emb), vec![0, 1]);
        let (ids, emb) = frame(&[0.1, 10.1, 30.0]);
        assert_eq!(t.update(&Frame::new(0, 2), &ids, &emb), vec![0, 1, 2]);
        // Person 1 leaves; after max_age frames unseen the track is retired.
        for _ in 0..4 {
            let (ids, emb) = frame(&[0.1, 30.0]);
            assert_eq!(t.update(&Frame::new(0, 2), &ids, &emb), vec![0, 2]);
        }
        assert_eq!(t.live_tracks(), 2);
        // Someone appearing where person 1 was, after retirement, is someone new.
        let (ids, emb) = frame(&[0.1, 10.1, 30.0]);
        assert_eq!(t.update(&Frame::new(0, 2), &ids, &emb), vec![0, 3, 2]);
    }

    #[test]
    fn memory_stays_bounded_in_an_endless_crowd() {
        let cfg = TrackerConfig {
            max_age: 5,
            max_tracks: 64,
            ..TrackerConfig::default()
        };
        let mut t = Tracker::new(cfg);
        for f in 0..2000 {
            // 40 people per frame, everyone new every frame (far from everyone before).
            let pos: Vec<f32> = (0..40).map(|p| (f * 1000 + p * 10) as f32).collect();
            let (ids, emb) = frame(&pos);
            t.update(&Frame::new(0, 2), &ids, &emb);
            assert!(t.live_tracks() <= 64);
        }
    }

    #[test]
    fn empty_frames_and_bad_rows_are_harmless() {
        let mut t = Tracker::new(TrackerConfig::default());
        let emb = FrameEmbeddings::from_views(&[None, None]).unwrap();
        assert!(t.update(&Frame::new(0, 2), &[], &emb).is_empty());
        // A member pointing past the rows, and a NaN row: a new id, no track, no panic.
        let view = Array2::from_shape_fn((1, 1), |_| f32::NAN);
        let emb = FrameEmbeddings::from_views(&[Some(view), None]).unwrap();
        let ids = vec![
            Identity {
                id: 0,
                confidence: 1.0,
                members: vec![(0, 0)],
            },
            Identity {
                id: 1,
                confidence: 1.0,
                members: vec![(0, 7), (5, 0)],
            },
        ];
        assert_eq!(t.update(&Frame::new(0, 2), &ids, &emb), vec![0, 1]);
        assert_eq!(t.live_tracks(), 0);
    }
}
