//! How a record's value is encoded where a transport carries bare bytes with a media type
//! (Kafka records and their `content-type` header): a JSON batch line / `FrameResult` object,
//! or the protobuf messages of [`crate::pb`]. The server and the load generator both name and
//! read formats through this one type.

/// A value's encoding, named by a `content-type` header.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ValueFormat {
    /// JSON (`application/json`): a SPEC §7 batch line, a `FrameResult` object.
    #[default]
    Json,
    /// Protobuf (`application/x-protobuf`): `crossview.v1.Batch`, `crossview.v1.FrameResult`.
    Protobuf,
}

impl ValueFormat {
    /// The `content-type` header value this format is written with.
    pub fn content_type(self) -> &'static str {
        match self {
            ValueFormat::Json => "application/json",
            ValueFormat::Protobuf => "application/x-protobuf",
        }
    }

    /// The format a `content-type` header names (parameters such as `; charset=utf-8` are
    /// ignored); `None` for one we do not read.
    pub fn from_content_type(v: &[u8]) -> Option<Self> {
        let v = std::str::from_utf8(v).ok()?;
        let media = v
            .split(';')
            .next()
            .unwrap_or("")
            .trim()
            .to_ascii_lowercase();
        match media.as_str() {
            "application/json" => Some(ValueFormat::Json),
            "application/x-protobuf"
            | "application/protobuf"
            | "application/vnd.google.protobuf" => Some(ValueFormat::Protobuf),
            _ => None,
        }
    }
}

/// `json` or `protobuf` (also `proto`), any case: the spelling of the command-line flags.
impl std::str::FromStr for ValueFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "json" => Ok(ValueFormat::Json),
            "protobuf" | "proto" => Ok(ValueFormat::Protobuf),
            _ => {
                let shown: String = s.chars().take(64).collect();
                Err(format!("'{shown}' is not json or protobuf"))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn content_types_and_flag_spellings() {
        let proto = ValueFormat::Protobuf;
        assert_eq!(
            ValueFormat::from_content_type(b"application/x-protobuf"),
            Some(proto)
        );
        assert_eq!(
            ValueFormat::from_content_type(b"Application/JSON; charset=utf-8"),
            Some(ValueFormat::Json)
        );
        assert_eq!(ValueFormat::from_content_type(b"text/plain"), None);
        assert_eq!(ValueFormat::from_content_type(b"\xff"), None);
        for f in [ValueFormat::Json, proto] {
            assert_eq!(
                ValueFormat::from_content_type(f.content_type().as_bytes()),
                Some(f)
            );
        }
        assert_eq!("protobuf".parse::<ValueFormat>().unwrap(), proto);
        assert_eq!("JSON".parse::<ValueFormat>().unwrap(), ValueFormat::Json);
        assert!("xml".parse::<ValueFormat>().is_err());
    }
}
