//! ROS 1 bags (format 2.0) as a stream of messages for [`super::bag::BagReader`]: the bag header, then
//! chunks (uncompressed, bz2 or lz4) holding connection and message records, then the index (connection
//! and chunk-info records) at the position the header names.
//!
//! Our own reader rather than the `rosbag` crate (0.6): that crate maps the whole file into memory (a
//! file truncated while mapped is a SIGBUS, not an error), asserts on chunk sizes (a panic on a hostile
//! file), and does not read a bag without its index, which is what a crashed recorder leaves. The format
//! itself is small (seven record types); decompression uses the well-kept `bzip2` (pure Rust backend) and
//! `lz4` (frame format, as roslz4 writes) crates.
//!
//! Messages come in file order, so two passes see the same indices. Connections are read from the index
//! first when there is one (a chunk may use a connection defined in an earlier chunk); a bag without an
//! index (`index_pos` 0, as a recording that was cut short leaves it) is read by scanning its chunks,
//! and a final record cut short ends the scan; both are reported in [`MessageSource::notes`]. Every
//! length is checked against the bytes left before anything is allocated.

use std::collections::HashMap;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::Path;
use std::sync::Arc;

use super::container::{open_file, BagError, Connection, MessageSource, RawMessage};
use super::container::{MAX_RECORD, MIN_RECORD};
use super::ros1;

const OP_MESSAGE: u8 = 0x02;
const OP_BAG_HEADER: u8 = 0x03;
const OP_INDEX: u8 = 0x04;
const OP_CHUNK: u8 = 0x05;
const OP_CHUNK_INFO: u8 = 0x06;
const OP_CONNECTION: u8 = 0x07;
/// Largest record header (connection headers carry message definitions: tens of KiB in practice).
const MAX_HEADER: u64 = 64 << 20;

/// A record's header fields (`name=value`).
struct Fields(Vec<(String, Vec<u8>)>);

impl Fields {
    fn parse(b: &[u8]) -> Result<Self, String> {
        let mut out = Vec::new();
        let mut p = 0usize;
        while p < b.len() {
            let n = le_u32(b, p).ok_or("field length cut short")? as usize;
            p += 4;
            let f = b
                .get(p..p.checked_add(n).ok_or("field length overflows")?)
                .ok_or_else(|| format!("field of {n} bytes runs past its header"))?;
            p += n;
            let eq = f
                .iter()
                .position(|&c| c == b'=')
                .ok_or("header field without '='")?;
            out.push((
                String::from_utf8_lossy(&f[..eq]).into_owned(),
                f[eq + 1..].to_vec(),
            ));
        }
        Ok(Fields(out))
    }

    fn get(&self, name: &str) -> Option<&[u8]> {
        self.0.iter().find(|(k, _)| k == name).map(|(_, v)| &v[..])
    }

    fn op(&self) -> Result<u8, String> {
        match self.get("op") {
            Some([op]) => Ok(*op),
            Some(_) => Err("'op' field is not one byte".into()),
            None => Err("record without 'op' field".into()),
        }
    }

    fn u32(&self, name: &str) -> Result<u32, String> {
        self.get(name)
            .and_then(|v| le_u32(v, 0).filter(|_| v.len() == 4))
            .ok_or_else(|| format!("missing or malformed '{name}' field"))
    }

    fn u64(&self, name: &str) -> Result<u64, String> {
        match self.get(name) {
            Some(v) if v.len() == 8 => Ok(u64::from_le_bytes(v.try_into().unwrap_or([0; 8]))),
            _ => Err(format!("missing or malformed '{name}' field")),
        }
    }

    fn string(&self, name: &str) -> Option<String> {
        self.get(name)
            .map(|v| String::from_utf8_lossy(v).into_owned())
    }

    /// A ROS time field (u32 seconds, u32 nanoseconds) in ns.
    fn time(&self, name: &str) -> Result<u64, String> {
        let t = self.u64(name)?;
        Ok((t & 0xffff_ffff) * 1_000_000_000 + (t >> 32))
    }
}

fn le_u32(b: &[u8], p: usize) -> Option<u32> {
    let s = b.get(p..p.checked_add(4)?)?;
    Some(u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
}

/// `pkg/Type` → `pkg/msg/Type`, the form rosbag2 and the `rosbags` package report ROS 1 types in.
fn ros1_type_name(ty: &str) -> String {
    match ty.split_once('/') {
        Some((pkg, t)) if !t.contains('/') => format!("{pkg}/msg/{t}"),
        _ => ty.to_string(),
    }
}

/// A connection record's data (a header block of topic, type, md5sum, message_definition…).
fn connection(fields: &Fields, data: &[u8]) -> Result<(u32, Connection), String> {
    let id = fields.u32("conn")?;
    let d = Fields::parse(data).map_err(|e| format!("connection {id}: {e}"))?;
    let topic = d
        .string("topic")
        .or_else(|| fields.string("topic"))
        .ok_or_else(|| format!("connection {id} has no topic"))?;
    let ty = d
        .string("type")
        .ok_or_else(|| format!("connection {id} ('{topic}') has no type"))?;
    let text = d.get("message_definition").unwrap_or(&[]).to_vec();
    let def = (!text.iter().all(u8::is_ascii_whitespace))
        .then(|| ros1::Definition::parse(&ty, &String::from_utf8_lossy(&text)).map(Arc::new));
    Ok((
        id,
        Connection {
            topic,
            schema_name: ros1_type_name(&ty),
            schema_encoding: "ros1msg".into(),
            schema_text: text,
            message_encoding: "ros1".into(),
            ros1: def,
        },
    ))
}

/// What a ROS 1 bag is read from: a file, or bytes in memory (the fuzz target).
pub(crate) trait ReadSeek: Read + Seek + Send {}
impl<T: Read + Seek + Send> ReadSeek for T {}

/// The messages of one ROS 1 bag in file order.
pub(crate) struct Ros1Source {
    file: String,
    r: BufReader<Box<dyn ReadSeek>>,
    len: u64,
    /// File offset of the next record.
    pos: u64,
    /// Where the chunk section ends (the index position, or the file's end without an index).
    end: u64,
    indexed: bool,
    /// Largest decompressed chunk accepted (from the file size, like the MCAP reader).
    chunk_limit: u64,
    conns: HashMap<u32, Arc<Connection>>,
    chunk: Vec<u8>,
    chunk_pos: usize,
    chunk_at: u64,
    notes: Vec<String>,
    done: bool,
}

impl Ros1Source {
    pub(crate) fn open(path: &Path) -> Result<Self, BagError> {
        let (file, f, len) = open_file(path)?;
        Self::from_reader(file, Box::new(f), len)
    }

    /// Reads a bag of `len` bytes from `source`; `file` names it in errors.
    pub(crate) fn from_reader(
        file: String,
        source: Box<dyn ReadSeek>,
        len: u64,
    ) -> Result<Self, BagError> {
        let mut s = Self {
            file,
            r: BufReader::new(source),
            len,
            pos: 0,
            end: len,
            indexed: false,
            chunk_limit: len.clamp(MIN_RECORD, MAX_RECORD),
            conns: HashMap::new(),
            chunk: Vec::new(),
            chunk_pos: 0,
            chunk_at: 0,
            notes: Vec::new(),
            done: false,
        };
        let mut magic = [0u8; 13];
        s.read_exact(&mut magic)?;
        if &magic != b"#ROSBAG V2.0\n" {
            return Err(s.err(0, "not a ROS 1 bag of format 2.0 (bad magic)"));
        }
        let Some((fields, _)) = s.record(false)? else {
            return Err(s.err(13, "no bag header record"));
        };
        let op = fields.op().map_err(|e| s.err(13, e))?;
        if op != OP_BAG_HEADER {
            return Err(s.err(
                13,
                format!("first record has op {op:#04x}, not the bag header"),
            ));
        }
        let index_pos = fields.u64("index_pos").map_err(|e| s.err(13, e))?;
        let chunks = fields.u32("chunk_count").unwrap_or(0);
        if index_pos == 0 {
            s.notes.push(
                "the bag has no index (index_pos 0: the recording was not closed, e.g. the recorder \
                 crashed): read by scanning its chunks"
                    .into(),
            );
        } else if index_pos < s.pos || index_pos > len {
            s.notes.push(format!(
                "the bag's index position {index_pos} lies outside the file ({len} bytes): read by \
                 scanning its chunks"
            ));
        } else {
            s.indexed = true;
            s.end = index_pos;
            s.read_index(index_pos)?;
            if chunks > 0 && s.conns.is_empty() {
                s.notes.push(format!(
                    "the index lists {chunks} chunks but no connection: connections read from the chunks"
                ));
            }
        }
        Ok(s)
    }

    fn err(&self, at: u64, reason: impl Into<String>) -> BagError {
        BagError::Format {
            file: self.file.clone(),
            at: format!("offset {at}"),
            reason: reason.into(),
        }
    }

    fn read_exact(&mut self, buf: &mut [u8]) -> Result<(), BagError> {
        let at = self.pos;
        self.r.read_exact(buf).map_err(|e| {
            if e.kind() == std::io::ErrorKind::UnexpectedEof {
                self.err(at, "truncated file")
            } else {
                BagError::Io {
                    file: self.file.clone(),
                    source: e,
                }
            }
        })?;
        self.pos += buf.len() as u64;
        Ok(())
    }

    fn read_u32(&mut self) -> Result<u64, BagError> {
        let mut b = [0u8; 4];
        self.read_exact(&mut b)?;
        Ok(u32::from_le_bytes(b) as u64)
    }

    /// A length-prefixed block of at most `max` bytes, checked against the file before allocating.
    fn block(&mut self, max: u64, what: &str) -> Result<Vec<u8>, BagError> {
        let at = self.pos;
        let n = self.read_u32()?;
        let left = self.len - self.pos;
        if n > left {
            return Err(self.err(
                at,
                format!("{what} of {n} bytes runs past the end of the file ({left} bytes left): truncated file"),
            ));
        }
        if n > max {
            return Err(self.err(
                at,
                format!("{what} of {n} bytes is beyond the {max}-byte limit"),
            ));
        }
        let mut v = vec![0u8; n as usize];
        self.read_exact(&mut v)?;
        Ok(v)
    }

    /// The next file-level record (header fields, data); `None` at the file's end. `skip_data` seeks
    /// over the data instead of reading it (index records, the bag header's padding).
    fn record(&mut self, skip_data: bool) -> Result<Option<(Fields, Vec<u8>)>, BagError> {
        if self.pos >= self.len {
            return Ok(None);
        }
        let at = self.pos;
        let header = self.block(MAX_HEADER, "record header")?;
        let fields = Fields::parse(&header).map_err(|e| self.err(at, e))?;
        let op = fields.op().map_err(|e| self.err(at, e))?;
        let skip = skip_data || op == OP_BAG_HEADER || op == OP_INDEX || op == OP_CHUNK_INFO;
        let data = if skip {
            let n = self.read_u32()?;
            if n > self.len - self.pos {
                return Err(self.err(
                    at,
                    format!(
                        "record data of {n} bytes runs past the end of the file: truncated file"
                    ),
                ));
            }
            self.r
                .seek_relative(n as i64)
                .map_err(|source| BagError::Io {
                    file: self.file.clone(),
                    source,
                })?;
            self.pos += n;
            Vec::new()
        } else {
            self.block(u64::MAX, "record data")?
        };
        Ok(Some((fields, data)))
    }

    /// Connections from the index section, then back to the first chunk.
    fn read_index(&mut self, index_pos: u64) -> Result<(), BagError> {
        let resume = self.pos;
        self.seek(index_pos)?;
        while let Some((fields, data)) = self.record(false)? {
            if fields.op().ok() == Some(OP_CONNECTION) {
                let (id, c) = connection(&fields, &data).map_err(|e| self.err(index_pos, e))?;
                self.conns.entry(id).or_insert_with(|| Arc::new(c));
            }
        }
        self.seek(resume)
    }

    fn seek(&mut self, pos: u64) -> Result<(), BagError> {
        self.r
            .seek(SeekFrom::Start(pos))
            .map_err(|source| BagError::Io {
                file: self.file.clone(),
                source,
            })?;
        self.pos = pos;
        Ok(())
    }

    /// Decompresses a chunk record's data into `self.chunk`.
    fn load_chunk(&mut self, at: u64, fields: &Fields, data: Vec<u8>) -> Result<(), BagError> {
        let size = fields.u32("size").map_err(|e| self.err(at, e))? as u64;
        let compression = fields.string("compression").unwrap_or_default();
        if size > self.chunk_limit {
            return Err(self.err(
                at,
                format!(
                    "chunk of {size} bytes uncompressed is beyond the {}-byte limit",
                    self.chunk_limit
                ),
            ));
        }
        let out = match compression.as_str() {
            "none" => Ok(data),
            "bz2" => inflate(bzip2::read::BzDecoder::new(&data[..]), size),
            "lz4" => match lz4::Decoder::new(&data[..]) {
                Ok(d) => inflate(d, size),
                Err(e) => Err(e.to_string()),
            },
            other => {
                return Err(self.err(
                    at,
                    format!("unknown chunk compression '{other}' (bz2, lz4 and none are read)"),
                ))
            }
        }
        .map_err(|e| self.err(at, format!("corrupt {compression} chunk: {e}")))?;
        if out.len() as u64 != size {
            return Err(self.err(
                at,
                format!("corrupt {compression} chunk: {} bytes after decompression, its header says {size}", out.len()),
            ));
        }
        self.chunk = out;
        self.chunk_pos = 0;
        self.chunk_at = at;
        Ok(())
    }

    /// The next message of the current chunk (registering connection records on the way).
    fn next_in_chunk(&mut self) -> Result<Option<RawMessage>, BagError> {
        while self.chunk_pos < self.chunk.len() {
            let at = self.chunk_pos;
            let where_ = |s: &Self, e: String| BagError::Format {
                file: s.file.clone(),
                at: format!("chunk at offset {}, byte {at}", s.chunk_at),
                reason: e,
            };
            let (fields, data, next) =
                chunk_record(&self.chunk, at).map_err(|e| where_(self, e))?;
            self.chunk_pos = next;
            let op = fields.op().map_err(|e| where_(self, e))?;
            match op {
                OP_CONNECTION => {
                    let (id, c) = connection(&fields, data).map_err(|e| where_(self, e))?;
                    self.conns.entry(id).or_insert_with(|| Arc::new(c));
                }
                OP_MESSAGE => {
                    let id = fields.u32("conn").map_err(|e| where_(self, e))?;
                    let t = fields.time("time").map_err(|e| where_(self, e))?;
                    let conn = self.conns.get(&id).cloned().ok_or_else(|| {
                        where_(
                            self,
                            format!(
                                "message on connection {id}, which no connection record defines"
                            ),
                        )
                    })?;
                    return Ok(Some(RawMessage {
                        conn,
                        log_time: t,
                        publish_time: t,
                        data: data.to_vec(),
                    }));
                }
                other => {
                    return Err(where_(
                        self,
                        format!("unexpected record op {other:#04x} inside a chunk"),
                    ))
                }
            }
        }
        Ok(None)
    }

    fn next_message(&mut self) -> Result<Option<RawMessage>, BagError> {
        loop {
            if let Some(m) = self.next_in_chunk()? {
                return Ok(Some(m));
            }
            if self.pos >= self.end {
                return Ok(None);
            }
            let at = self.pos;
            let record = match self.record(false) {
                Ok(Some(r)) => r,
                Ok(None) => return Ok(None),
                Err(BagError::Format { reason, .. })
                    if !self.indexed && reason.contains("truncated") =>
                {
                    self.notes.push(format!(
                        "the recording ends inside a record at offset {at} ({} bytes not read): it was cut short",
                        self.len - at
                    ));
                    return Ok(None);
                }
                Err(e) => return Err(e),
            };
            let (fields, data) = record;
            match fields.op().map_err(|e| self.err(at, e))? {
                OP_CHUNK => self.load_chunk(at, &fields, data)?,
                OP_INDEX => {}
                OP_CONNECTION => {
                    let (id, c) = connection(&fields, &data).map_err(|e| self.err(at, e))?;
                    self.conns.entry(id).or_insert_with(|| Arc::new(c));
                }
                // Without an index position, the index section is where the chunks end.
                OP_CHUNK_INFO => return Ok(None),
                op => {
                    return Err(self.err(
                        at,
                        format!("unexpected record op {op:#04x} in the chunk section"),
                    ))
                }
            }
        }
    }
}

/// A record inside a decompressed chunk: (fields, data, offset of the next record).
fn chunk_record(b: &[u8], at: usize) -> Result<(Fields, &[u8], usize), String> {
    let hl = le_u32(b, at).ok_or("record header length cut short")? as usize;
    let h = b
        .get(at + 4..(at + 4).saturating_add(hl))
        .ok_or_else(|| format!("record header of {hl} bytes runs past the chunk"))?;
    let fields = Fields::parse(h)?;
    let dp = at + 4 + hl;
    let dl = le_u32(b, dp).ok_or("record data length cut short")? as usize;
    let data = b
        .get(dp + 4..(dp + 4).saturating_add(dl))
        .ok_or_else(|| format!("record data of {dl} bytes runs past the chunk"))?;
    Ok((fields, data, dp + 4 + dl))
}

/// Decompresses at most `size + 1` bytes (one more shows a chunk that lies about its size).
fn inflate(r: impl Read, size: u64) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    out.try_reserve_exact(size as usize)
        .map_err(|e| format!("cannot allocate {size} bytes: {e}"))?;
    r.take(size + 1)
        .read_to_end(&mut out)
        .map_err(|e| e.to_string())?;
    Ok(out)
}

impl MessageSource for Ros1Source {
    fn notes(&self) -> Vec<String> {
        self.notes.clone()
    }
}

impl Iterator for Ros1Source {
    type Item = Result<RawMessage, BagError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        match self.next_message() {
            Ok(Some(m)) => Some(Ok(m)),
            Ok(None) => {
                self.done = true;
                None
            }
            Err(e) => {
                self.done = true;
                Some(Err(e))
            }
        }
    }
}
