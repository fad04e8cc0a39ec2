//! The consume loop: input records in, through [`Service::push`], their offsets tracked until
//! their frames' results are produced (or they were refused), dead letters out.
use std::sync::Arc;
use std::time::Duration;

use rdkafka::message::{Header, Message, OwnedHeaders};
use rdkafka::producer::FutureRecord;
use rdkafka::util::Timeout;

use crossview_core::capture::CaptureTime;

use super::codec::{content_type, decode};
use super::config::TimestampSource;
use super::{Kafka, ValueFormat, now_ms, wake};
use crate::error::{Error, Result};
use crate::locks::lock;

/// How long consumption may wait for room (frames in flight at their cap) before stream time
/// runs on by the wall clock: frames that wait on stream time may be what fills it, waiting
/// for records the wait keeps unread. Far above the time an encoder needs to free a slot.
const STUCK: Duration = Duration::from_secs(1);

/// One consumed input record.
struct Record<'a> {
    key: Option<&'a [u8]>,
    payload: Option<&'a [u8]>,
    partition: i32,
    offset: i64,
    /// Read here before (below the highest offset consumed before the last revocation).
    redelivered: bool,
    /// The record's timestamp, ms since the Unix epoch (create or log-append time).
    stamp_ms: Option<i64>,
}

/// What became of one input record.
enum Handled {
    /// Consumed (its offset closes once its frame's result is produced, or now if refused).
    Next,
    /// The service is shutting down: the record stays uncommitted (re-read later).
    Stop,
}

impl Kafka {
    /// The consume loop, until shutdown begins.
    pub(super) async fn consume(self: Arc<Self>) {
        let stop = self.service.shutting_down();
        tokio::pin!(stop);
        loop {
            let msg = tokio::select! {
                m = self.consumer.recv() => m,
                _ = &mut stop => break,
            };
            let msg = match msg {
                Ok(m) => m,
                Err(e) => {
                    tracing::warn!(error = %e, "kafka: consume error");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            };
            let (partition, offset) = (msg.partition(), msg.offset());
            let stamp = msg.timestamp().to_millis();
            let redelivered = {
                let mut o = lock(&self.offsets);
                let Some(redelivered) = o.consumed(partition, offset) else {
                    // Fetched before its partition was revoked: left to the owner.
                    continue;
                };
                // Stream time moves to the record's stamp before its batch is pushed.
                if o.deliver(partition, stamp, std::time::Instant::now(), now_ms()) == Some(false) {
                    self.metrics().kafka_untimed();
                }
                redelivered
            };
            let record = Record {
                key: msg.key(),
                payload: msg.payload(),
                partition,
                offset,
                redelivered,
                stamp_ms: stamp,
            };
            let format = content_type(&msg).unwrap_or(Ok(self.config.input_format));
            if let Handled::Stop = self.handle(&record, format).await {
                break;
            }
            self.backpressure().await;
        }
    }

    /// Waits while too many frames wait for their results. Frames whose timeouts run on
    /// stream time could wait for records this wait keeps unread: after [`STUCK`] without
    /// room, stream time runs on by the wall clock (every 100 ms) until there is room.
    async fn backpressure(&self) {
        let started = std::time::Instant::now();
        let mut warned = false;
        let mut last_run = started;
        while lock(&self.offsets).in_flight() >= self.config.max_in_flight
            && self.service.accepting()
        {
            let now = std::time::Instant::now();
            if now.duration_since(started) >= STUCK
                && now.duration_since(last_run) >= Duration::from_millis(100)
            {
                last_run = now;
                let scenes = lock(&self.offsets).stuck(now);
                if !warned && !scenes.is_empty() {
                    tracing::warn!(
                        ?scenes,
                        "kafka: no room for frames in flight for {STUCK:?}; stream time runs \
                         on by the wall clock"
                    );
                    warned = true;
                }
                wake(&self.service, &scenes);
            }
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    }

    async fn handle(&self, r: &Record<'_>, format: Result<ValueFormat>) -> Handled {
        let (partition, offset) = (r.partition, r.offset);
        let record_time = (self.config.timestamps == TimestampSource::Record)
            .then(|| r.stamp_ms?.checked_mul(1_000_000))
            .flatten()
            .and_then(|ns| CaptureTime::from_unix_nanos(ns).ok());
        let (scene, batch) = match format.and_then(|f| decode(r.key, r.payload, f, record_time)) {
            Ok(v) => v,
            Err(e) => {
                if r.redelivered {
                    // Refused (and dead-lettered) when first read.
                    self.metrics().kafka_redelivered();
                } else {
                    self.metrics().kafka_record("malformed");
                    tracing::debug!(partition, offset, error = %e, "kafka: malformed record skipped");
                    self.dead_letter(r, &e).await;
                }
                lock(&self.offsets).done(partition, offset);
                return Handled::Next;
            }
        };
        self.enter_scene(&scene, partition);
        // Held under the frame it will be published as (after the camera's clock offset, or
        // its capture time's tick), so that frame's result closes it.
        let frame_id = self
            .service
            .frame_of(&scene, &batch)
            .unwrap_or(batch.frame_id);
        let created = lock(&self.offsets).hold(&scene, frame_id, partition, offset);
        loop {
            match self.service.push(&scene, batch.clone()) {
                Ok(_) => {
                    self.metrics().kafka_record("accepted");
                    return Handled::Next;
                }
                Err(Error::ResourceExhausted(_) | Error::Overloaded { .. })
                    if self.service.accepting() =>
                {
                    // Overload: wait (backpressure on the partition), never drop or shed.
                    tokio::time::sleep(Duration::from_millis(10)).await;
                }
                Err(Error::Unavailable(_)) => return Handled::Stop,
                Err(e) => {
                    let again = r.redelivered
                        && matches!(
                            e,
                            Error::LateBatch { .. }
                                | Error::Core(crossview_core::Error::DuplicateBatch { .. })
                        );
                    if created {
                        // No result will hold it; a frame already pending here keeps it
                        // (its result closes the offset).
                        lock(&self.offsets).unhold(&scene, frame_id, partition, offset);
                    }
                    if again {
                        // Read before, its frame already produced: not a loss.
                        self.metrics().kafka_redelivered();
                        tracing::debug!(partition, offset, "kafka: re-delivered batch dropped");
                    } else {
                        self.metrics().kafka_record("rejected");
                        tracing::debug!(partition, offset, error = %e, "kafka: record rejected");
                        self.dead_letter(r, &e).await;
                    }
                    return Handled::Next;
                }
            }
        }
    }

    /// The first record of `scene` since its partition was (re)assigned: the scene starts
    /// afresh just past its last produced frame (none: from scratch), its sync timeouts on
    /// the partition's stream time. A scene nobody serves is not tracked (its records are
    /// refused): hostile keys never grow the bookkeeping.
    fn enter_scene(&self, scene: &str, partition: i32) {
        let Some(s) = self.service.find_scene(scene) else {
            return;
        };
        let (last, clock) = {
            let mut o = lock(&self.offsets);
            // Not the scene's first record here, or (never both) its partition not owned.
            let (Some(last), Some(clock)) = (o.enter_scene(scene, partition), o.clock(partition))
            else {
                return;
            };
            (last, clock)
        };
        let dropped = s.restart(last);
        s.follow_stream(clock);
        tracing::info!(
            scene,
            partition,
            ?last,
            dropped,
            "kafka: scene (re)starts here"
        );
    }

    /// Copies a refused record to the dead-letter topic, if there is one.
    async fn dead_letter(&self, r: &Record<'_>, error: &Error) {
        let (key, payload) = (r.key, r.payload);
        let Some(topic) = &self.config.dead_letter_topic else {
            return;
        };
        let reason = error.to_string();
        let source = format!("{}/{}/{}", self.config.input_topic, r.partition, r.offset);
        let headers = OwnedHeaders::new()
            .insert(Header {
                key: "crossview-error",
                value: Some(reason.as_bytes()),
            })
            .insert(Header {
                key: "crossview-source",
                value: Some(source.as_bytes()),
            });
        let mut record = FutureRecord::<[u8], [u8]>::to(topic).headers(headers);
        if let Some(k) = key {
            record = record.key(k);
        }
        if let Some(p) = payload {
            record = record.payload(p);
        }
        if let Err((e, _)) = self
            .producer
            .send(record, Timeout::After(Duration::from_secs(10)))
            .await
        {
            tracing::warn!(error = %e, %source, "kafka: dead-letter produce failed");
        }
    }
}
