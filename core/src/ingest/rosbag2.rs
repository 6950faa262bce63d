//! rosbag2 bags as a stream of messages for [`super::bag::BagReader`]: a folder with `metadata.yaml` and
//! its storage files (SQLite `.db3`, as Foxy to Humble record by default, or MCAP), or a bare `.db3`.
//!
//! The `.db3` is read with `rusqlite` and SQLite bundled (the reference implementation of the format;
//! native only, the browser receives decoded data). Messages are CDR as in MCAP; topics are joined to
//! messages by the database's own topic ids, never by the order `metadata.yaml` lists them in (a v4
//! bag's metadata lists them in another order than the ids, which is how other readers lose its
//! messages). Compression: file-level zstd (`.db3.zstd`) is inflated to a temporary file first;
//! message-level zstd is recognised per message from its magic bytes (a CDR payload never starts with
//! them), so a bare `.db3` of a compressed bag reads too. Old type names (`sensor_msgs/Image`, Crystal
//! era) are normalised to `pkg/msg/Type`.

use std::collections::{HashMap, VecDeque};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use rusqlite::OpenFlags;
use serde::Deserialize;

use super::container::{BagError, Connection, MessageSource, RawMessage, ZSTD_MAGIC};
use super::mcap::McapSource;
use super::ros;

/// Largest message after zstd inflation (SQLite's own blob limit is 1 GB).
const MAX_MESSAGE: u64 = 1 << 30;
/// Rows fetched per query (keeps memory to a few messages while streaming by id).
const PAGE: i64 = 64;

#[derive(Deserialize)]
struct MetadataFile {
    rosbag2_bagfile_information: Metadata,
}

/// The fields of `metadata.yaml` we use (every version from 1 to 9 has them or defaults them).
#[derive(Deserialize, Default)]
#[serde(default)]
struct Metadata {
    storage_identifier: String,
    relative_file_paths: Vec<String>,
    compression_format: String,
    compression_mode: String,
}

fn format_err(file: &Path, at: &str, reason: impl Into<String>) -> BagError {
    BagError::Format {
        file: file.display().to_string(),
        at: at.into(),
        reason: reason.into(),
    }
}

/// Parses `metadata.yaml` text (the fuzz target calls this).
pub fn parse_metadata(text: &str) -> Result<(String, Vec<String>, String), String> {
    let m: MetadataFile = serde_saphyr::from_str(text).map_err(|e| e.to_string())?;
    let m = m.rosbag2_bagfile_information;
    let compression = if m.compression_format.is_empty() {
        String::new()
    } else {
        format!(
            "{} ({})",
            m.compression_format,
            m.compression_mode.to_lowercase()
        )
    };
    Ok((m.storage_identifier, m.relative_file_paths, compression))
}

/// Opens a rosbag2 folder, its `metadata.yaml`, or a single `.db3` / `.db3.zstd` file.
pub(crate) fn open(path: &Path) -> Result<Box<dyn MessageSource>, BagError> {
    let io = |source| BagError::Io {
        file: path.display().to_string(),
        source,
    };
    let (dir, single) = if path.is_dir() {
        (path.to_path_buf(), None)
    } else if path.file_name().is_some_and(|n| n == "metadata.yaml") {
        (path.parent().unwrap_or(Path::new(".")).to_path_buf(), None)
    } else {
        (PathBuf::new(), Some(path.to_path_buf()))
    };
    let mut notes = Vec::new();
    let files: Vec<PathBuf> = if let Some(f) = single {
        vec![f]
    } else {
        let meta = dir.join("metadata.yaml");
        if meta.is_file() {
            let text = std::fs::read_to_string(&meta).map_err(io)?;
            let (storage, files, compression) =
                parse_metadata(&text).map_err(|e| format_err(&meta, "metadata.yaml", e))?;
            if !compression.is_empty() {
                notes.push(format!("compression: {compression}"));
            }
            if !matches!(storage.as_str(), "sqlite3" | "mcap" | "") {
                return Err(format_err(
                    &meta,
                    "storage_identifier",
                    format!("storage '{storage}' is not read (sqlite3 and mcap are)"),
                ));
            }
            let mut out = Vec::new();
            for f in files {
                let p = Path::new(&f);
                // Paths stay inside the bag's folder.
                if p.is_absolute()
                    || p.components()
                        .any(|c| matches!(c, std::path::Component::ParentDir))
                {
                    return Err(format_err(
                        &meta,
                        "relative_file_paths",
                        format!("'{f}' leaves the bag's folder"),
                    ));
                }
                out.push(dir.join(p));
            }
            if out.is_empty() {
                return Err(format_err(
                    &meta,
                    "relative_file_paths",
                    "the bag lists no storage file",
                ));
            }
            out
        } else {
            notes.push(
                "no metadata.yaml: read the folder's .db3 and .mcap files in name order".into(),
            );
            let mut out: Vec<PathBuf> = std::fs::read_dir(&dir)
                .map_err(io)?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    let n = p.to_string_lossy();
                    n.ends_with(".db3") || n.ends_with(".mcap") || n.ends_with(".db3.zstd")
                })
                .collect();
            out.sort();
            if out.is_empty() {
                return Err(format_err(
                    &dir,
                    "folder",
                    "no metadata.yaml and no .db3 or .mcap file",
                ));
            }
            out
        }
    };
    Ok(Box::new(Rosbag2Source {
        files: files.into(),
        current: None,
        notes,
    }))
}

/// One storage file being read.
enum Storage {
    Sqlite(Db3Source),
    Mcap(McapSource),
}

/// The messages of a rosbag2 bag's files, one file after the other.
struct Rosbag2Source {
    files: VecDeque<PathBuf>,
    current: Option<Storage>,
    notes: Vec<String>,
}

impl Rosbag2Source {
    fn open_next(&mut self) -> Option<Result<(), BagError>> {
        let path = self.files.pop_front()?;
        let kind = match super::container::detect(&path) {
            Ok(k) => k,
            Err(e) => return Some(Err(e)),
        };
        Some(match kind {
            super::container::BagFormat::Mcap => McapSource::open(&path).map(|s| {
                self.current = Some(Storage::Mcap(s));
            }),
            super::container::BagFormat::Rosbag2 => Db3Source::open(&path).map(|s| {
                if let Some(n) = &s.note {
                    self.notes.push(n.clone());
                }
                self.current = Some(Storage::Sqlite(s));
            }),
            super::container::BagFormat::Ros1 => Err(format_err(
                &path,
                "storage file",
                "a ROS 1 bag inside a rosbag2 folder",
            )),
        })
    }
}

impl MessageSource for Rosbag2Source {
    fn notes(&self) -> Vec<String> {
        self.notes.clone()
    }
}

impl Iterator for Rosbag2Source {
    type Item = Result<RawMessage, BagError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            let next = match self.current.as_mut() {
                Some(Storage::Sqlite(s)) => s.next(),
                Some(Storage::Mcap(s)) => s.next(),
                None => None,
            };
            match next {
                Some(Err(e)) => {
                    self.files.clear();
                    self.current = None;
                    return Some(Err(e));
                }
                Some(ok) => return Some(ok),
                None => {
                    self.current = None;
                    if let Err(e) = self.open_next()? {
                        self.files.clear();
                        return Some(Err(e));
                    }
                }
            }
        }
    }
}

/// A temporary file removed when dropped (a `.db3.zstd` inflated for SQLite).
struct TempFile(PathBuf);

impl Drop for TempFile {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

/// The messages of one `.db3` in insertion (id) order, fetched a page at a time.
struct Db3Source {
    path: PathBuf,
    db: rusqlite::Connection,
    topics: HashMap<i64, Arc<Connection>>,
    last_id: i64,
    page: VecDeque<RawMessage>,
    done: bool,
    note: Option<String>,
    _temp: Option<TempFile>,
}

impl Db3Source {
    fn open(path: &Path) -> Result<Self, BagError> {
        let sql = |at: &str, e: rusqlite::Error| {
            format_err(path, at, format!("not a readable rosbag2 database: {e}"))
        };
        let mut head = [0u8; 4];
        let zstd = std::fs::File::open(path)
            .and_then(|mut f| f.read_exact(&mut head))
            .is_ok()
            && head == ZSTD_MAGIC;
        let (db_path, temp, note) = if zstd {
            let t = inflate_file(path)?;
            (
                t.0.clone(),
                Some(t),
                Some(format!(
                    "{}: zstd-compressed file inflated to a temporary file",
                    path.display()
                )),
            )
        } else {
            (path.to_path_buf(), None, None)
        };
        let db = rusqlite::Connection::open_with_flags(
            &db_path,
            OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
        )
        .map_err(|e| sql("open", e))?;
        // Catch a corrupt page where SQLite would otherwise read it as data.
        let _ = db.pragma_update(None, "cell_size_check", true);
        let mut definitions: HashMap<String, (String, Vec<u8>)> = HashMap::new();
        if let Ok(mut st) = db.prepare(
            "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions",
        ) {
            let rows = st.query_map([], |r| {
                Ok((
                    r.get::<_, String>(0)?,
                    r.get::<_, String>(1)?,
                    r.get::<_, String>(2)?,
                ))
            });
            if let Ok(rows) = rows {
                for (ty, enc, text) in rows.flatten() {
                    definitions.insert(ros::canonical_type(&ty), (enc, text.into_bytes()));
                }
            }
        }
        let mut topics = HashMap::new();
        {
            let mut st = db
                .prepare("SELECT id, name, type, serialization_format FROM topics")
                .map_err(|e| sql("topics table", e))?;
            let rows = st
                .query_map([], |r| {
                    Ok((
                        r.get::<_, i64>(0)?,
                        r.get::<_, String>(1)?,
                        r.get::<_, String>(2)?,
                        r.get::<_, String>(3)?,
                    ))
                })
                .map_err(|e| sql("topics table", e))?;
            for row in rows {
                let (id, name, ty, fmt) = row.map_err(|e| sql("topics table", e))?;
                let ty = ros::canonical_type(&ty);
                let (enc, text) = definitions.get(&ty).cloned().unwrap_or_default();
                topics.insert(id, Arc::new(Connection::cdr(&name, &ty, &enc, text, &fmt)));
            }
        }
        Ok(Self {
            path: path.to_path_buf(),
            db,
            topics,
            last_id: i64::MIN,
            page: VecDeque::new(),
            done: false,
            note,
            _temp: temp,
        })
    }

    fn fetch(&mut self) -> Result<(), BagError> {
        let path = self.path.clone();
        let sql = |e: rusqlite::Error| format_err(&path, "messages table", e.to_string());
        let mut st = self
            .db
            .prepare_cached(
                "SELECT id, topic_id, timestamp, data FROM messages WHERE id > ?1 ORDER BY id LIMIT ?2",
            )
            .map_err(sql)?;
        let mut rows = st.query((self.last_id, PAGE)).map_err(sql)?;
        let mut n = 0;
        while let Some(r) = rows.next().map_err(sql)? {
            let id: i64 = r.get(0).map_err(sql)?;
            let topic: i64 = r.get(1).map_err(sql)?;
            let t: i64 = r.get(2).map_err(sql)?;
            let blob = r.get_ref(3).map_err(sql)?;
            let data = blob.as_blob().map_err(|e| sql(e.into()))?;
            let at = format!("messages row id {id}");
            let conn = self.topics.get(&topic).cloned().ok_or_else(|| {
                format_err(
                    &path,
                    &at,
                    format!("topic id {topic} is not in the topics table"),
                )
            })?;
            let data = if data.starts_with(ZSTD_MAGIC) {
                inflate_message(data).map_err(|e| format_err(&path, &at, e))?
            } else {
                data.to_vec()
            };
            let t = u64::try_from(t)
                .map_err(|_| format_err(&path, &at, format!("negative timestamp {t}")))?;
            self.last_id = id;
            self.page.push_back(RawMessage {
                conn,
                log_time: t,
                publish_time: t,
                data,
            });
            n += 1;
        }
        if n < PAGE {
            self.done = true;
        }
        Ok(())
    }
}

impl Iterator for Db3Source {
    type Item = Result<RawMessage, BagError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.page.is_empty() && !self.done {
            if let Err(e) = self.fetch() {
                self.done = true;
                self.page.clear();
                return Some(Err(e));
            }
        }
        self.page.pop_front().map(Ok)
    }
}

fn inflate_message(data: &[u8]) -> Result<Vec<u8>, String> {
    let d = zstd::stream::read::Decoder::new(data).map_err(|e| format!("zstd message: {e}"))?;
    let mut out = Vec::new();
    d.take(MAX_MESSAGE + 1)
        .read_to_end(&mut out)
        .map_err(|e| format!("corrupt zstd message: {e}"))?;
    if out.len() as u64 > MAX_MESSAGE {
        return Err(format!("zstd message inflates beyond {MAX_MESSAGE} bytes"));
    }
    Ok(out)
}

/// Inflates a zstd-compressed storage file to a temporary file (written under a temporary name and
/// removed when the reader is dropped).
fn inflate_file(path: &Path) -> Result<TempFile, BagError> {
    static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let tmp = std::env::temp_dir().join(format!("silvr-rosbag2-{}-{n}.db3", std::process::id()));
    let io = |source| BagError::Io {
        file: path.display().to_string(),
        source,
    };
    let temp = TempFile(tmp.clone());
    let src = std::fs::File::open(path).map_err(io)?;
    let mut dec = zstd::stream::read::Decoder::new(std::io::BufReader::new(src)).map_err(io)?;
    let mut out = std::fs::File::create(&tmp).map_err(io)?;
    std::io::copy(&mut dec, &mut out)
        .map_err(|e| format_err(path, "zstd stream", format!("corrupt compressed file: {e}")))?;
    Ok(temp)
}
