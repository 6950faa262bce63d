//! A recording as one stream of messages, whatever its container: an MCAP file ([`super::mcap`]), a ROS 1
//! bag of format 2.0 ([`super::ros1bag`]) or a rosbag2 folder or `.db3` file ([`super::rosbag2`]). The
//! format is recognised from the content (magic bytes, or a folder's `metadata.yaml`), never from the
//! extension.
//!
//! Every message comes with its connection (topic, type, encodings, schema text) and a position in file
//! order, so two passes over a bag see the same messages with the same indices. ROS 1 messages of the
//! types we decode are rewritten as CDR from the definitions their bag carries ([`super::ros1`]), so
//! [`BagMessage::decode`] serves every container with the same decoders. Every failure is a [`BagError`]
//! naming the file and, for a damaged container, where and how it is damaged.

use std::collections::BTreeMap;
use std::io::Read;
use std::path::Path;
use std::sync::Arc;

pub use super::container::{bag_bytes, detect, BagError, BagFormat, Connection};
use super::container::{MessageSource, ROS1_MAGIC};
use super::ros::{self, DecodeError, RosMessage};

/// One message of a bag with its connection.
#[derive(Clone, Debug)]
pub struct BagMessage {
    conn: Arc<Connection>,
    log_time: u64,
    publish_time: u64,
    data: Vec<u8>,
    /// ROS 1 messages of a type we decode: the message as CDR, or why it could not be rewritten.
    cdr: Option<Result<Vec<u8>, String>>,
    /// 0-based position in file order.
    pub index: u64,
}

/// Why a message was not decoded.
#[derive(Clone, Debug, PartialEq)]
pub enum Skip {
    /// The channel's message encoding is neither `cdr` nor `ros1`.
    NotCdr(String),
    /// The channel has no schema (or, in a ROS 1 bag, an empty message definition), so the type is
    /// unknown.
    NoSchema,
    /// A schema we have no decoder for.
    UnknownType(String),
}

impl std::fmt::Display for Skip {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Skip::NotCdr(e) => write!(f, "message encoding '{e}' is not cdr"),
            Skip::NoSchema => write!(f, "channel has no schema"),
            Skip::UnknownType(t) => write!(f, "no decoder for {t}"),
        }
    }
}

impl BagMessage {
    pub fn topic(&self) -> &str {
        &self.conn.topic
    }

    /// Schema name (e.g. `sensor_msgs/msg/PointCloud2`); "" when the channel has none.
    pub fn schema_name(&self) -> &str {
        &self.conn.schema_name
    }

    /// Schema encoding (`ros2msg`, `ros2idl`, `omgidl`, `ros1msg`…); "" when none.
    pub fn schema_encoding(&self) -> &str {
        &self.conn.schema_encoding
    }

    /// The schema text (for display), if any.
    pub fn schema_text(&self) -> Option<&[u8]> {
        Some(&self.conn.schema_text[..]).filter(|t| !t.is_empty())
    }

    /// Message encoding as stored (`cdr` for ROS 2, `ros1` for ROS 1).
    pub fn message_encoding(&self) -> &str {
        &self.conn.message_encoding
    }

    /// Receive time in ns since the UNIX epoch (the recorder's clock).
    pub fn log_time(&self) -> u64 {
        self.log_time
    }

    pub fn publish_time(&self) -> u64 {
        self.publish_time
    }

    /// The serialized payload as stored (CDR for ROS 2, ROS 1 serialisation for ROS 1).
    pub fn data(&self) -> &[u8] {
        &self.data
    }

    /// Why this message would be skipped, or `None` when [`ros::decode`] handles it.
    pub fn skip_reason(&self) -> Option<Skip> {
        let ros1 = match self.message_encoding() {
            "cdr" => false,
            "ros1" => true,
            e => return Some(Skip::NotCdr(e.to_string())),
        };
        let name = self.schema_name();
        if name.is_empty() || (ros1 && self.conn.ros1.is_none()) {
            return Some(Skip::NoSchema);
        }
        if !ros::is_known_type(name) {
            return Some(Skip::UnknownType(name.to_string()));
        }
        None
    }

    /// Decodes a known type (`Ok(Ok(msg))`), reports why it is skipped (`Ok(Err(skip))`), or the decode
    /// error of a known type (`Err`).
    pub fn decode(&self) -> Result<Result<RosMessage<'_>, Skip>, DecodeError> {
        if let Some(skip) = self.skip_reason() {
            return Ok(Err(skip));
        }
        let payload = match &self.cdr {
            None => &self.data[..],
            Some(Ok(cdr)) => &cdr[..],
            Some(Err(reason)) => return Err(DecodeError::Ros1(reason.clone())),
        };
        match ros::decode(self.schema_name(), payload) {
            Some(r) => r.map(Ok),
            None => Ok(Err(Skip::UnknownType(self.schema_name().to_string()))),
        }
    }
}

/// Streams the messages of a bag in file order.
pub struct BagReader {
    file: String,
    format: BagFormat,
    source: Box<dyn MessageSource>,
    index: u64,
    failed: bool,
}

impl BagReader {
    /// Opens a bag of any supported format (see [`detect`]).
    pub fn open(path: &Path) -> Result<Self, BagError> {
        let format = detect(path)?;
        let source: Box<dyn MessageSource> = match format {
            BagFormat::Mcap => Box::new(super::mcap::McapSource::open(path)?),
            BagFormat::Ros1 => Box::new(super::ros1bag::Ros1Source::open(path)?),
            BagFormat::Rosbag2 => super::rosbag2::open(path)?,
        };
        Ok(Self {
            file: path.display().to_string(),
            format,
            source,
            index: 0,
            failed: false,
        })
    }

    /// Streams the messages of the MCAP that `source` yields (`len` bytes: it bounds the record
    /// length); `name` names it in errors. The fuzz target and the writer's tests read bytes in memory
    /// this way.
    pub fn from_reader(
        name: impl Into<String>,
        source: impl Read + Send + 'static,
        len: u64,
    ) -> Self {
        let file = name.into();
        Self {
            source: Box::new(super::mcap::McapSource::from_reader(
                file.clone(),
                source,
                len,
            )),
            file,
            format: BagFormat::Mcap,
            index: 0,
            failed: false,
        }
    }

    /// Reads a bag held in memory (MCAP or ROS 1, recognised from its first bytes); `name` names it in
    /// errors. The fuzz targets read this way.
    pub fn from_bytes(name: impl Into<String>, bytes: Vec<u8>) -> Result<Self, BagError> {
        let file = name.into();
        let len = bytes.len() as u64;
        if bytes.starts_with(ROS1_MAGIC) {
            let source = super::ros1bag::Ros1Source::from_reader(
                file.clone(),
                Box::new(std::io::Cursor::new(bytes)),
                len,
            )?;
            return Ok(Self {
                file,
                format: BagFormat::Ros1,
                source: Box::new(source),
                index: 0,
                failed: false,
            });
        }
        Ok(Self::from_reader(file, std::io::Cursor::new(bytes), len))
    }

    /// The file name used in errors.
    pub fn file(&self) -> &str {
        &self.file
    }

    pub fn format(&self) -> BagFormat {
        self.format
    }

    /// What the reader had to assume or work around so far (e.g. a missing index).
    pub fn notes(&self) -> Vec<String> {
        self.source.notes()
    }

    /// A decode error of `msg` as a [`BagError`] naming the file and the message.
    pub fn decode_error(&self, msg: &BagMessage, source: DecodeError) -> BagError {
        BagError::Decode {
            file: self.file.clone(),
            index: msg.index,
            topic: msg.topic().to_string(),
            log_time: msg.log_time(),
            source: Box::new(source),
        }
    }
}

impl Iterator for BagReader {
    type Item = Result<BagMessage, BagError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.failed {
            return None;
        }
        let raw = match self.source.next()? {
            Ok(raw) => raw,
            Err(e) => {
                self.failed = true;
                return Some(Err(e));
            }
        };
        let mut msg = BagMessage {
            conn: raw.conn,
            log_time: raw.log_time,
            publish_time: raw.publish_time,
            data: raw.data,
            cdr: None,
            index: self.index,
        };
        self.index += 1;
        if msg.message_encoding() == "ros1" && msg.skip_reason().is_none() {
            msg.cdr = Some(match &msg.conn.ros1 {
                Some(Ok(def)) => def.to_cdr(&msg.data),
                Some(Err(e)) => Err(format!("message definition: {e}")),
                None => Err("no message definition".into()),
            });
        }
        Some(Ok(msg))
    }
}

/// Per-topic counts of a bag.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TopicSummary {
    pub schema_name: String,
    pub message_encoding: String,
    pub messages: u64,
    /// Messages of this topic that were decoded (known type, CDR, no error).
    pub decoded: u64,
    pub first_log_time: u64,
    pub last_log_time: u64,
}

/// What a bag holds, from one pass over it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BagSummary {
    pub topics: BTreeMap<String, TopicSummary>,
    pub messages: u64,
    /// Log-time span (ns) over all messages; `None` for an empty bag.
    pub span: Option<(u64, u64)>,
    /// Messages not decoded, by reason.
    pub skipped: BTreeMap<String, u64>,
    /// Decode errors of known types (the first few in full in `first_errors`).
    pub decode_errors: u64,
    pub first_errors: Vec<String>,
    /// The container format.
    pub format: Option<BagFormat>,
    /// What the reader had to assume or work around (see [`BagReader::notes`]).
    pub notes: Vec<String>,
}

impl BagSummary {
    /// Duration of the bag in seconds (0 for fewer than two distinct times).
    pub fn duration(&self) -> f64 {
        self.span.map_or(0.0, |(a, b)| (b - a) as f64 * 1e-9)
    }
}

/// Reads every message of the bag, decoding the known types, and summarises it. A damaged container
/// is an error; a message that fails to decode is counted (see [`BagSummary::decode_errors`]).
pub fn summarize(path: &Path) -> Result<BagSummary, BagError> {
    let mut reader = BagReader::open(path)?;
    let mut s = BagSummary {
        format: Some(reader.format()),
        ..BagSummary::default()
    };
    for msg in reader.by_ref() {
        let msg = msg?;
        let t = msg.log_time();
        s.messages += 1;
        s.span = Some(s.span.map_or((t, t), |(a, b)| (a.min(t), b.max(t))));
        let topic = s
            .topics
            .entry(msg.topic().to_string())
            .or_insert_with(|| TopicSummary {
                schema_name: msg.schema_name().to_string(),
                message_encoding: msg.message_encoding().to_string(),
                first_log_time: t,
                last_log_time: t,
                ..Default::default()
            });
        topic.messages += 1;
        topic.first_log_time = topic.first_log_time.min(t);
        topic.last_log_time = topic.last_log_time.max(t);
        match msg.decode() {
            Ok(Ok(_)) => topic.decoded += 1,
            Ok(Err(skip)) => *s.skipped.entry(skip.to_string()).or_insert(0) += 1,
            Err(e) => {
                s.decode_errors += 1;
                if s.first_errors.len() < 5 {
                    let e = BagError::Decode {
                        file: path.display().to_string(),
                        index: msg.index,
                        topic: msg.topic().to_string(),
                        log_time: t,
                        source: Box::new(e),
                    };
                    s.first_errors.push(e.to_string());
                }
            }
        }
    }
    s.notes = reader.notes();
    Ok(s)
}
