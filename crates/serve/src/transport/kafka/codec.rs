//! Record values: input batches (JSON line or protobuf `Batch`, chosen by the `content-type`
//! header) and output results (JSON with `producer`, or protobuf `FrameResult`).
use rdkafka::message::Message;

use crossview_api::convert::{batch_from_pb, result_to_pb};
use crossview_api::pb;
use crossview_core::Batch;
use crossview_core::capture::CaptureTime;
use prost::Message as _;

use super::ValueFormat;
use crate::error::{Error, Result};

/// The format a record's `content-type` header names: `None` without the header, an error
/// for a type we do not read.
pub(super) fn content_type<M: Message>(msg: &M) -> Option<Result<ValueFormat>> {
    use rdkafka::message::Headers;
    let headers = msg.headers()?;
    let h = headers
        .iter()
        .find(|h| h.key.eq_ignore_ascii_case("content-type"))?;
    let v = h.value.unwrap_or_default();
    Some(ValueFormat::from_content_type(v).ok_or_else(|| {
        Error::invalid(
            "content-type",
            format!(
                "'{}' is not application/json or application/x-protobuf",
                crate::echo::truncate_echo(&String::from_utf8_lossy(v))
            ),
        )
    }))
}

/// A record's scene (its key) and batch (its value: a SPEC §7 batch line, or a protobuf
/// `Batch` whose `scene`, if set, must equal the key). With `record_time` (`--kafka-timestamp
/// record`), a batch without a capture time takes that one.
pub(super) fn decode(
    key: Option<&[u8]>,
    payload: Option<&[u8]>,
    format: ValueFormat,
    record_time: Option<CaptureTime>,
) -> Result<(String, Batch)> {
    let scene = key
        .filter(|k| !k.is_empty())
        .ok_or_else(|| Error::invalid("key", "a record needs its scene name as key"))?;
    let scene = std::str::from_utf8(scene)
        .map_err(|_| Error::invalid("key", "the scene name is not UTF-8"))?
        .to_string();
    let value = payload.ok_or_else(|| Error::invalid("value", "empty record"))?;
    let invalid = |e: serde_json::Error| Error::invalid("value", e.to_string());
    let mut batch: Batch = match (format, record_time) {
        (ValueFormat::Json, None) => serde_json::from_slice(value).map_err(invalid)?,
        (ValueFormat::Json, Some(t)) => {
            // A line without `time` (it may have no frame id either) takes the record's.
            let mut v: serde_json::Value = serde_json::from_slice(value).map_err(invalid)?;
            if let Some(o) = v.as_object_mut()
                && !o.contains_key("time")
            {
                o.insert("time".into(), serde_json::json!(t.to_rfc3339()));
            }
            serde_json::from_value(v).map_err(invalid)?
        }
        (ValueFormat::Protobuf, _) => {
            let pb = pb::Batch::decode(value)
                .map_err(|e| Error::invalid("value", format!("not a protobuf Batch: {e}")))?;
            if !pb.scene.is_empty() && pb.scene != scene {
                return Err(Error::invalid(
                    "scene",
                    format!(
                        "the batch names scene '{}' but the record key is '{}'",
                        crate::echo::truncate_echo(&pb.scene),
                        crate::echo::truncate_echo(&scene)
                    ),
                ));
            }
            batch_from_pb(pb)?.1
        }
    };
    if batch.time.is_none() {
        batch.time = record_time;
    }
    Ok((scene, batch))
}

/// A result's record value: JSON with `producer` added, or the protobuf `FrameResult` (whose
/// producer is in the headers only).
pub(super) fn encode_result(
    result: &crossview_api::types::FrameResult,
    format: ValueFormat,
    producer: &str,
    epoch: u64,
) -> Result<Vec<u8>> {
    match format {
        ValueFormat::Protobuf => Ok(result_to_pb(result).encode_to_vec()),
        ValueFormat::Json => {
            // Written straight out (no intermediate `serde_json::Value`: that tree cost a
            // share of a replica's CPU per frame).
            let value = WithProducer {
                result,
                producer: Producer {
                    id: producer,
                    epoch,
                },
            };
            serde_json::to_vec(&value).map_err(|e| Error::internal_from("encode result", e))
        }
    }
}

/// A JSON result with the replica that produced it.
#[derive(serde::Serialize)]
struct WithProducer<'a> {
    #[serde(flatten)]
    result: &'a crossview_api::types::FrameResult,
    producer: Producer<'a>,
}

/// `producer` of a JSON result: the replica's id and its assignment's epoch.
#[derive(serde::Serialize)]
struct Producer<'a> {
    id: &'a str,
    epoch: u64,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transport::kafka::KafkaConfig;
    use crossview_core::Batch;

    #[test]
    fn a_json_result_is_the_result_plus_its_producer() {
        let r = crossview_api::types::FrameResult {
            scene: "lab".into(),
            frame_id: 7,
            time: None,
            complete: false,
            missing_cameras: vec!["c1".into()],
            fenced_cameras: vec![],
            identities: vec![],
            latency_ms: 3.5,
            error: None,
            error_kind: None,
            status: Default::default(),
            model_version: Some("1@abc".into()),
        };
        let bytes = encode_result(&r, ValueFormat::Json, "replica-1", 42).unwrap();
        let mut v: serde_json::Value = serde_json::from_slice(&bytes).unwrap();
        let producer = v.as_object_mut().unwrap().remove("producer").unwrap();
        assert_eq!(
            producer,
            serde_json::json!({"id": "replica-1", "epoch": 42})
        );
        assert_eq!(v, serde_json::to_value(&r).unwrap());
        let back: crossview_api::types::FrameResult = serde_json::from_slice(&bytes).unwrap();
        assert_eq!(back, r);
    }

    #[test]
    fn records_need_a_scene_key_and_a_batch_line() {
        let line = br#"{"camera":"c0","frame_id":3,"detections":[]}"#;
        let json = ValueFormat::Json;
        let (scene, b) = decode(Some(b"lab"), Some(line), json, None).unwrap();
        assert_eq!((scene.as_str(), b.frame_id), ("lab", 3));
        assert!(decode(None, Some(line), json, None).is_err());
        assert!(decode(Some(&[0xff]), Some(line), json, None).is_err());
        assert!(decode(Some(b"lab"), Some(b"{not json"), json, None).is_err());
        assert!(decode(Some(b"lab"), None, json, None).is_err());
        // With the record's time: a line with neither a frame id nor a time takes it; one
        // with its own time keeps it.
        let t = CaptureTime::from_unix_nanos(1_796_515_200_100_000_000).unwrap();
        let bare = br#"{"camera": "c0", "detections": []}"#;
        assert!(decode(Some(b"lab"), Some(bare), json, None).is_err());
        let (_, b) = decode(Some(b"lab"), Some(bare), json, Some(t)).unwrap();
        assert_eq!((b.frame_id, b.time), (0, Some(t)));
        let own = br#"{"camera": "c0", "time": 5.0, "detections": []}"#;
        let (_, b) = decode(Some(b"lab"), Some(own), json, Some(t)).unwrap();
        assert_eq!(b.time.map(CaptureTime::unix_nanos), Some(5_000_000_000));
        let p = KafkaConfig::parse_property("sasl.password=x=y").unwrap();
        assert_eq!(p, ("sasl.password".into(), "x=y".into()));
        assert!(KafkaConfig::parse_property("novalue").is_err());
        let mut c = KafkaConfig::new("b:9092", "in", "out", "g");
        c.properties.push(p);
        assert!(!format!("{c:?}").contains("x=y"));
    }

    #[test]
    fn protobuf_values_decode_and_must_agree_with_the_key() {
        let batch = Batch {
            camera: "c0".into(),
            frame_id: 7,
            time: None,
            detections: vec![],
        };
        let proto = ValueFormat::Protobuf;
        let bytes = crossview_api::convert::batch_to_pb("lab", &batch).encode_to_vec();
        let (scene, b) = decode(Some(b"lab"), Some(&bytes), proto, None).unwrap();
        assert_eq!(
            (scene.as_str(), b.camera.as_str(), b.frame_id),
            ("lab", "c0", 7)
        );
        let unnamed = crossview_api::convert::batch_to_pb("", &batch).encode_to_vec();
        assert_eq!(
            decode(Some(b"lab"), Some(&unnamed), proto, None).unwrap().0,
            "lab"
        );
        assert!(decode(Some(b"other"), Some(&bytes), proto, None).is_err());
        assert!(decode(Some(b"lab"), Some(b"\xff\xff\xff"), proto, None).is_err());
        // A JSON line read as protobuf (and the other way round) is malformed, not a panic.
        let line = br#"{"camera":"c0","frame_id":3,"detections":[]}"#;
        assert!(decode(Some(b"lab"), Some(line), proto, None).is_err());
        assert!(decode(Some(b"lab"), Some(&bytes), ValueFormat::Json, None).is_err());
    }
}
