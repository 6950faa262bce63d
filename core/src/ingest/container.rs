//! What every bag container shares, below the readers of each ([`super::mcap`], [`super::ros1bag`],
//! [`super::rosbag2`]) and the stream over them ([`super::bag`]): the error type, a connection (topic,
//! type, encodings, schema), a message as a container yields it, and recognising a bag from its first
//! bytes.

use std::io::Read;
use std::path::Path;
use std::sync::Arc;

use mcap::McapError;
use thiserror::Error;

use super::ros::DecodeError;
use super::ros1;

/// Largest record (or decompressed chunk) accepted regardless of file size, so a corrupt length field
/// cannot make a reader allocate without bound. rosbag2 writes chunks of a few MiB.
pub(crate) const MAX_RECORD: u64 = 4 << 30;
/// Smallest record limit, so legitimately well-compressed chunks of small files still read.
pub(crate) const MIN_RECORD: u64 = 256 << 20;

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
    /// A ROS 1 bag or rosbag2 storage is damaged or not what it claims: `at` says where (a byte offset,
    /// a record, a table), `reason` what is wrong.
    #[error("{file}: {at}: {reason}")]
    Format {
        file: String,
        at: String,
        reason: String,
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

/// The containers [`super::bag::BagReader`] reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BagFormat {
    /// One MCAP file (ROS 2 profile).
    Mcap,
    /// A ROS 1 bag, format 2.0.
    Ros1,
    /// A rosbag2 folder (`metadata.yaml` + `.db3` or `.mcap` files) or a bare `.db3` file.
    Rosbag2,
}

impl BagFormat {
    pub fn name(self) -> &'static str {
        match self {
            BagFormat::Mcap => "MCAP",
            BagFormat::Ros1 => "ROS 1 bag (format 2.0)",
            BagFormat::Rosbag2 => "rosbag2",
        }
    }
}

pub(crate) const MCAP_MAGIC: &[u8] = b"\x89MCAP0\r\n";
pub(crate) const ROS1_MAGIC: &[u8] = b"#ROSBAG V2.0\n";
const SQLITE_MAGIC: &[u8] = b"SQLite format 3\0";
pub(crate) const ZSTD_MAGIC: &[u8] = &[0x28, 0xb5, 0x2f, 0xfd];

/// Recognises a bag from its content: a folder is a rosbag2 bag; a file by its first bytes.
pub fn detect(path: &Path) -> Result<BagFormat, BagError> {
    let file = path.display().to_string();
    let io = |source| BagError::Io {
        file: file.clone(),
        source,
    };
    let meta = std::fs::metadata(path).map_err(io)?;
    if meta.is_dir() || path.file_name().is_some_and(|n| n == "metadata.yaml") {
        return Ok(BagFormat::Rosbag2);
    }
    let mut head = [0u8; 16];
    let mut f = std::fs::File::open(path).map_err(io)?;
    let mut n = 0;
    while n < head.len() {
        match f.read(&mut head[n..]).map_err(io)? {
            0 => break,
            k => n += k,
        }
    }
    let head = &head[..n];
    if head.starts_with(MCAP_MAGIC) {
        Ok(BagFormat::Mcap)
    } else if head.starts_with(ROS1_MAGIC) {
        Ok(BagFormat::Ros1)
    } else if head.starts_with(SQLITE_MAGIC) || head.starts_with(ZSTD_MAGIC) {
        Ok(BagFormat::Rosbag2)
    } else if head.starts_with(b"#ROSBAG V") {
        let version: String = head[9..]
            .iter()
            .take_while(|&&b| b != b'\n')
            .map(|&b| b as char)
            .collect();
        Err(BagError::Format {
            file,
            at: "bag header".into(),
            reason: format!(
                "ROS bag format {version} is not supported (only 2.0, written since ROS C Turtle)"
            ),
        })
    } else {
        Err(BagError::Format {
            file,
            at: "first bytes".into(),
            reason: "not a bag: neither MCAP, a ROS 1 bag (format 2.0), an SQLite .db3 nor a rosbag2 folder"
                .into(),
        })
    }
}

/// Opens a bag file: its name for errors, the file, and its length (which bounds record sizes).
pub(crate) fn open_file(path: &Path) -> Result<(String, std::fs::File, u64), BagError> {
    let file = path.display().to_string();
    let io = |source| BagError::Io {
        file: file.clone(),
        source,
    };
    let f = std::fs::File::open(path).map_err(io)?;
    let len = f.metadata().map_err(io)?.len();
    Ok((file, f, len))
}

/// Bytes a bag occupies (a folder: its files), for throughput reports.
pub fn bag_bytes(path: &Path) -> Result<u64, BagError> {
    let io = |source| BagError::Io {
        file: path.display().to_string(),
        source,
    };
    let meta = std::fs::metadata(path).map_err(io)?;
    if !meta.is_dir() {
        return Ok(meta.len());
    }
    let mut total = 0;
    for e in std::fs::read_dir(path).map_err(io)? {
        let e = e.map_err(io)?;
        let m = e.metadata().map_err(io)?;
        if m.is_file() {
            total += m.len();
        }
    }
    Ok(total)
}

/// A topic of a bag and how its messages are encoded, shared by all its messages.
#[derive(Debug)]
pub struct Connection {
    pub topic: String,
    /// Type name as `pkg/msg/Type` (ROS 1 and old rosbag2 names normalised) or as the MCAP stores it.
    pub schema_name: String,
    /// `ros2msg`, `ros2idl`, `ros1msg`…; "" when none.
    pub schema_encoding: String,
    /// The schema / message definition text (may be empty).
    pub schema_text: Vec<u8>,
    /// `cdr` (ROS 2) or `ros1`.
    pub message_encoding: String,
    /// ROS 1: the parsed message definition (or why it does not parse); `None` when the connection has
    /// no definition.
    pub(crate) ros1: Option<Result<Arc<ros1::Definition>, String>>,
}

impl Connection {
    /// A ROS 2 (CDR) connection.
    pub(crate) fn cdr(
        topic: &str,
        schema_name: &str,
        schema_encoding: &str,
        schema_text: Vec<u8>,
        message_encoding: &str,
    ) -> Self {
        Self {
            topic: topic.to_string(),
            schema_name: schema_name.to_string(),
            schema_encoding: schema_encoding.to_string(),
            schema_text,
            message_encoding: message_encoding.to_string(),
            ros1: None,
        }
    }
}

/// A message as a container yields it, before transcoding.
pub(crate) struct RawMessage {
    pub conn: Arc<Connection>,
    pub log_time: u64,
    pub publish_time: u64,
    pub data: Vec<u8>,
}

/// What a container reader yields; `notes` are facts about the file a user should see (e.g. a ROS 1
/// bag without its index, read by scanning its chunks).
pub(crate) trait MessageSource:
    Iterator<Item = Result<RawMessage, BagError>> + Send
{
    fn notes(&self) -> Vec<String> {
        Vec::new()
    }
}

/// The message of a caught panic (a third-party reader's, on a corrupt file), for the error that reports it.
pub(crate) fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "panic".into())
}
