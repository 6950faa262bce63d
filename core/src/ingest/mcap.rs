//! MCAP bags (ROS 2 profile) as a stream of messages for [`super::bag::BagReader`].
//!
//! Reading is linear with the `mcap` crate's streaming reader, so memory scales with the largest chunk,
//! not the file, and indexed and unindexed files (no summary section, e.g. a recording that was cut
//! short) read the same way. Chunks may be uncompressed, zstd or lz4; chunk CRCs are checked.

use std::collections::HashMap;
use std::io::{BufReader, Read};
use std::panic::AssertUnwindSafe;
use std::path::Path;
use std::sync::Arc;

use mcap::sans_io::LinearReaderOptions;
use mcap::McapError;

use super::container::{
    open_file, BagError, Connection, MessageSource, RawMessage, MAX_RECORD, MIN_RECORD,
};

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

/// The messages of one MCAP file in file order.
pub(crate) struct McapSource {
    file: String,
    inner: mcap::io::MessageReader<Box<dyn Read + Send>>,
    /// Our connection per MCAP channel id, built once.
    channels: HashMap<u16, Arc<Connection>>,
    failed: bool,
}

impl McapSource {
    pub(crate) fn open(path: &Path) -> Result<Self, BagError> {
        let (file, f, len) = open_file(path)?;
        Ok(Self::from_reader(file, BufReader::new(f), len))
    }

    pub(crate) fn from_reader(file: String, source: impl Read + Send + 'static, len: u64) -> Self {
        let limit = len.clamp(MIN_RECORD, MAX_RECORD);
        // Check each chunk's CRC before yielding any of its messages, so a corrupt chunk yields nothing
        // and its records are never parsed.
        let options = LinearReaderOptions::default()
            .with_prevalidate_chunk_crcs(true)
            .with_record_length_limit(usize::try_from(limit).unwrap_or(usize::MAX));
        let source: Box<dyn Read + Send> = Box::new(source);
        Self {
            file,
            inner: mcap::io::MessageReader::new_with_options(source, options),
            channels: HashMap::new(),
            failed: false,
        }
    }
}

impl MessageSource for McapSource {}

impl Iterator for McapSource {
    type Item = Result<RawMessage, BagError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.failed {
            return None;
        }
        let next = std::panic::catch_unwind(AssertUnwindSafe(|| self.inner.next()));
        let next = match next {
            Ok(next) => next?,
            Err(payload) => {
                self.failed = true;
                return Some(Err(BagError::ReaderPanic {
                    file: self.file.clone(),
                    detail: super::container::panic_message(payload.as_ref()),
                }));
            }
        };
        match next {
            Ok(m) => {
                let ch = &m.channel;
                let conn = self
                    .channels
                    .entry(ch.id)
                    .or_insert_with(|| {
                        let (name, enc, text) =
                            ch.schema.as_ref().map_or(("", "", Vec::new()), |s| {
                                (s.name.as_str(), s.encoding.as_str(), s.data.to_vec())
                            });
                        Arc::new(Connection::cdr(
                            &ch.topic,
                            name,
                            enc,
                            text,
                            &ch.message_encoding,
                        ))
                    })
                    .clone();
                Some(Ok(RawMessage {
                    conn,
                    log_time: m.log_time,
                    publish_time: m.publish_time,
                    data: m.data.into_owned(),
                }))
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
