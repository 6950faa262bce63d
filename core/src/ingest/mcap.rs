//! MCAP bags (ROS 2 profile): a streaming message iterator over a file, decoding by schema name, and a
//! summary of what a bag holds.
//!
//! Reading is linear with the `mcap` crate's streaming reader, so memory scales with the largest chunk,
//! not the file, and indexed and unindexed files (no summary section, e.g. a recording that was cut
//! short) read the same way. Chunks may be uncompressed, zstd or lz4; chunk CRCs are checked. Every
//! failure is a [`BagError`] naming the file and whether it looks truncated or corrupt.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufReader, Read};
use std::panic::AssertUnwindSafe;
use std::path::Path;

use mcap::sans_io::LinearReaderOptions;
use mcap::McapError;
use thiserror::Error;

use super::ros::{self, DecodeError, RosMessage};

/// Largest record (or decompressed chunk) accepted regardless of file size, so a corrupt length field
/// cannot make the reader allocate without bound. rosbag2 writes chunks of a few MiB.
const MAX_RECORD: u64 = 4 << 30;
/// Smallest record limit, so legitimately well-compressed chunks of small files still read.
const MIN_RECORD: u64 = 256 << 20;

/// What went wrong reading a bag. Every variant names the file.
#[derive(Debug, Error)]
pub enum BagError {
    #[error("{file}: {source}")]
    Io {
        file: String,
        #[source]
        source: std::io::Error,
    },
    /// The container itself is damaged: `kind` says how (truncated, corrupt chunk, unknown compression…).
    #[error("{file}: {kind}: {source}")]
    Container {
        file: String,
        kind: &'static str,
        #[source]
        source: McapError,
    },
    /// The `mcap` crate panicked on an inconsistent record (mcap 0.26 overflows on a record longer than
    /// its uncompressed chunk when the chunk has no CRC); caught so a bad file stays an error.
    #[error("{file}: corrupt MCAP: the reader failed on an inconsistent record ({detail})")]
    ReaderPanic { file: String, detail: String },
    /// Writing a bag failed in the container layer.
    #[error("{file}: writing MCAP: {source}")]
    Write {
        file: String,
        #[source]
        source: McapError,
    },
    /// The bag is usable as a container but not for what was asked (missing topic, wrong type, …).
    #[error("{file}: {reason}")]
    Invalid { file: String, reason: String },
    /// A message of a known type did not decode.
    #[error("{file}: message #{index} on '{topic}' at log time {log_time} ns: {source}")]
    Decode {
        file: String,
        index: u64,
        topic: String,
        log_time: u64,
        /// Boxed to keep `Result<_, BagError>` small.
        #[source]
        source: Box<DecodeError>,
    },
}

/// A short classification of an MCAP error for people reading logs.
fn classify(e: &McapError) -> &'static str {
    match e {
        McapError::UnexpectedEof => "truncated file",
        McapError::UnexpectedEoc => "corrupt chunk (record runs past the chunk end)",
        McapError::BadChunkCrc { .. } => "corrupt chunk (CRC mismatch)",
        McapError::DecompressionError(_) => "corrupt chunk (decompression failed)",
        McapError::BadChunkLength { .. } | McapError::ChunkTooLarge(_) => {
            "corrupt chunk (bad length)"
        }
        McapError::UnsupportedCompression(_) => "unknown chunk compression",
        McapError::BadMagic => "not an MCAP file (bad magic)",
        McapError::BadFooter => "corrupt footer",
        McapError::RecordTooLarge { .. } => {
            "record length beyond the limit (corrupt length field?)"
        }
        McapError::UnknownChannel(..) | McapError::UnknownSchema(..) => {
            "message or channel refers to an undeclared channel or schema"
        }
        McapError::ConflictingChannels(_) | McapError::ConflictingSchemas(_) => {
            "conflicting channel or schema records"
        }
        McapError::Parse(_) => "malformed record",
        McapError::Io(_) => "I/O error (or corrupt compressed stream)",
        _ => "invalid MCAP",
    }
}

/// One message of a bag with its channel metadata.
#[derive(Clone, Debug)]
pub struct BagMessage {
    inner: mcap::Message<'static>,
    /// 0-based position in file order.
    pub index: u64,
}

/// Why a message was not decoded.
#[derive(Clone, Debug, PartialEq)]
pub enum Skip {
    /// The channel's message encoding is not `cdr`.
    NotCdr(String),
    /// The channel has no schema, so the type is unknown.
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
        &self.inner.channel.topic
    }

    /// Schema name (e.g. `sensor_msgs/msg/PointCloud2`); "" when the channel has none.
    pub fn schema_name(&self) -> &str {
        self.inner
            .channel
            .schema
            .as_ref()
            .map_or("", |s| s.name.as_str())
    }

    /// Schema encoding (`ros2msg`, `ros2idl`, `omgidl`…); "" when none.
    pub fn schema_encoding(&self) -> &str {
        self.inner
            .channel
            .schema
            .as_ref()
            .map_or("", |s| s.encoding.as_str())
    }

    /// The schema text (for display), if any.
    pub fn schema_text(&self) -> Option<&[u8]> {
        self.inner.channel.schema.as_ref().map(|s| &s.data[..])
    }

    /// Message encoding (`cdr` for ROS 2).
    pub fn message_encoding(&self) -> &str {
        &self.inner.channel.message_encoding
    }

    /// Receive time in ns since the UNIX epoch (rosbag2 writes the recorder's clock here).
    pub fn log_time(&self) -> u64 {
        self.inner.log_time
    }

    pub fn publish_time(&self) -> u64 {
        self.inner.publish_time
    }

    /// The serialized payload (CDR for ROS 2).
    pub fn data(&self) -> &[u8] {
        &self.inner.data
    }

    /// Why this message would be skipped, or `None` when [`ros::decode`] handles it.
    pub fn skip_reason(&self) -> Option<Skip> {
        if self.message_encoding() != "cdr" {
            return Some(Skip::NotCdr(self.message_encoding().to_string()));
        }
        let name = self.schema_name();
        if name.is_empty() {
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
        match ros::decode(self.schema_name(), self.data()) {
            Some(r) => r.map(Ok),
            None => Ok(Err(Skip::UnknownType(self.schema_name().to_string()))),
        }
    }
}

/// Streams the messages of an MCAP file in file order.
pub struct BagReader {
    file: String,
    inner: mcap::io::MessageReader<Box<dyn Read + Send>>,
    index: u64,
    failed: bool,
}

impl BagReader {
    pub fn open(path: &Path) -> Result<Self, BagError> {
        let file = path.display().to_string();
        let io = |source| BagError::Io {
            file: file.clone(),
            source,
        };
        let f = File::open(path).map_err(io)?;
        let len = f.metadata().map_err(io)?.len();
        Ok(Self::from_reader(file, BufReader::new(f), len))
    }

    /// Streams the messages of the MCAP that `source` yields (`len` bytes: it sets the record length
    /// limit, see [`MAX_RECORD`]); `name` names it in errors. [`Self::open`] reads a file this way; the
    /// fuzz target reads bytes in memory.
    pub fn from_reader(
        name: impl Into<String>,
        source: impl Read + Send + 'static,
        len: u64,
    ) -> Self {
        let limit = len.clamp(MIN_RECORD, MAX_RECORD);
        // Check each chunk's CRC before yielding any of its messages, so a corrupt chunk yields nothing
        // and its records are never parsed.
        let options = LinearReaderOptions::default()
            .with_prevalidate_chunk_crcs(true)
            .with_record_length_limit(usize::try_from(limit).unwrap_or(usize::MAX));
        let source: Box<dyn Read + Send> = Box::new(source);
        Self {
            file: name.into(),
            inner: mcap::io::MessageReader::new_with_options(source, options),
            index: 0,
            failed: false,
        }
    }

    /// The file name used in errors.
    pub fn file(&self) -> &str {
        &self.file
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
        let next = std::panic::catch_unwind(AssertUnwindSafe(|| self.inner.next()));
        let next = match next {
            Ok(next) => next?,
            Err(payload) => {
                self.failed = true;
                let detail = payload
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| payload.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "panic".into());
                return Some(Err(BagError::ReaderPanic {
                    file: self.file.clone(),
                    detail,
                }));
            }
        };
        match next {
            Ok(inner) => {
                let msg = BagMessage {
                    inner,
                    index: self.index,
                };
                self.index += 1;
                Some(Ok(msg))
            }
            Err(source) => {
                self.failed = true;
                Some(Err(BagError::Container {
                    file: self.file.clone(),
                    kind: classify(&source),
                    source,
                }))
            }
        }
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
    let reader = BagReader::open(path)?;
    let mut s = BagSummary::default();
    for msg in reader {
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
    Ok(s)
}
