//! Where a dataset's files come from. Natively a folder; in the studio's worker the files a user dropped,
//! an archive written by `silvr pack`, or files fetched over HTTP. The loader (`train::data`) reads through
//! [`Source`] only, so the native binary and the browser share one loader and one set of errors, each
//! naming the file as the user knows it (`dataset/images/0001.png`, `submap.tar:images/0001.png`).
//!
//! The archive is a plain POSIX tar (no compression: the images are PNG or JPEG already), so a user can
//! inspect or unpack it with `tar tf` / `tar xf`.

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::dataset::DatasetError;

/// Largest archive or set of dropped files the studio reads (the browser holds them in memory).
pub const MAX_BYTES: u64 = 3 << 30;

/// A dataset's files, named by `/`-separated paths relative to the dataset root.
pub trait Source: Sync {
    /// The bytes of `rel`.
    fn read(&self, rel: &str) -> Result<Cow<'_, [u8]>, DatasetError>;
    /// Whether `rel` exists.
    fn exists(&self, rel: &str) -> bool;
    /// How messages name `rel`.
    fn path(&self, rel: &str) -> PathBuf;
    /// How messages name the whole source (the folder, archive or dropped folder).
    fn root(&self) -> PathBuf;
}

/// A folder on disk, read the way [`Files`] are: a name that leaves the root is refused (absolute, `..`
/// above the root, or through a symbolic link that resolves outside it), and so is what is not a regular
/// file (a FIFO would block, a device never end) or holds more than [`MAX_BYTES`]; files are read with
/// their size checked before the buffer is reserved.
///
/// The root is the folder itself ([`Dir::new`]) unless the caller widens it to an ancestor
/// ([`Dir::within`]): silvr's submap and poses outputs name their world's images
/// `../../dataset/images/…`, which only a root holding both can read.
pub struct Dir {
    /// The folder names are relative to (as given, for messages).
    folder: PathBuf,
    /// The folder within the root, normalised (`""`: the root itself).
    base: String,
    /// Where every read must stay, as given and resolved (symbolic links followed).
    root: PathBuf,
    canonical_root: PathBuf,
}

impl Dir {
    /// The folder `root`, confined to itself.
    pub fn new(root: impl Into<PathBuf>) -> Dir {
        let root = root.into();
        Dir {
            folder: root.clone(),
            base: String::new(),
            canonical_root: root.canonicalize().unwrap_or_else(|_| root.clone()),
            root,
        }
    }

    /// The folder `folder`, whose names may reach anything under `root`, an ancestor of it (or itself).
    pub fn within(folder: &Path, root: &Path) -> Result<Dir, DatasetError> {
        let bad = |detail: String| DatasetError::Format {
            path: folder.to_path_buf(),
            detail,
        };
        let io = |source| DatasetError::Io {
            path: folder.to_path_buf(),
            source,
        };
        let canonical_root = root.canonicalize().map_err(|source| DatasetError::Io {
            path: root.to_path_buf(),
            source,
        })?;
        let inside = folder.canonicalize().map_err(io)?;
        let base = inside
            .strip_prefix(&canonical_root)
            .map_err(|_| bad(format!("is not inside the data root {}", root.display())))?;
        let base = base
            .components()
            .map(|c| c.as_os_str().to_string_lossy())
            .collect::<Vec<_>>()
            .join("/");
        Ok(Dir {
            folder: folder.to_path_buf(),
            base,
            root: root.to_path_buf(),
            canonical_root,
        })
    }

    /// The file `rel` names, checked: inside the root, after every symbolic link, and a regular file.
    fn resolve(&self, rel: &str) -> Result<PathBuf, DatasetError> {
        let shown = self.path(rel);
        let joined = if self.base.is_empty() {
            rel.to_string()
        } else {
            format!("{}/{rel}", self.base)
        };
        let leaves = || DatasetError::Format {
            path: shown.clone(),
            detail: format!(
                "the path leaves the dataset's root {} (absolute, or `..` above it){}",
                self.root.display(),
                if self.base.is_empty() {
                    "; silvr's submap and poses outputs read their world's images from beside \
                     them: give a data root holding both (--data-root)"
                } else {
                    ""
                }
            ),
        };
        if rel.starts_with(['/', '\\']) || rel.contains(':') {
            return Err(leaves());
        }
        let key = normalise(&joined).ok_or_else(leaves)?;
        let real = self
            .canonical_root
            .join(&key)
            .canonicalize()
            .map_err(|source| DatasetError::Io {
                path: shown.clone(),
                source,
            })?;
        if !real.starts_with(&self.canonical_root) {
            return Err(DatasetError::Format {
                path: shown,
                detail: format!(
                    "a symbolic link leads outside the dataset's root {} (to {})",
                    self.root.display(),
                    real.display()
                ),
            });
        }
        Ok(real)
    }
}

impl Source for Dir {
    fn read(&self, rel: &str) -> Result<Cow<'_, [u8]>, DatasetError> {
        let real = self.resolve(rel)?;
        read_bounded(&real, MAX_BYTES)
            .map(Cow::Owned)
            .map_err(|e| match e {
                // Name the file as the dataset names it, not where its links led.
                DatasetError::Io { source, .. } => DatasetError::Io {
                    path: self.path(rel),
                    source,
                },
                DatasetError::Format { detail, .. } => DatasetError::Format {
                    path: self.path(rel),
                    detail,
                },
                other => other,
            })
    }

    /// Whether something is at `rel`. A name that is refused (it leaves the root) or is not a regular
    /// file "exists" too, so that reading it says why instead of the frame being skipped as missing.
    fn exists(&self, rel: &str) -> bool {
        match self.resolve(rel) {
            Ok(p) => p.exists(),
            Err(e) => matches!(e, DatasetError::Format { .. }),
        }
    }

    fn path(&self, rel: &str) -> PathBuf {
        self.folder.join(rel)
    }

    fn root(&self) -> PathBuf {
        self.folder.clone()
    }
}

/// Files held in memory: an unpacked archive, or the files of a dropped folder.
///
/// An archive is held once: its entries are ranges of the one buffer it was read into (a 1 GiB archive
/// costs 1 GiB, not the archive plus a copy of every file).
#[derive(Default)]
pub struct Files {
    /// The archive's or folder's name, for messages.
    pub name: String,
    files: BTreeMap<String, Blob>,
    /// The archive every file is a range of, while that holds (see [`Files::as_tar`]).
    archive: Option<Arc<Vec<u8>>>,
}

/// One file's bytes: its own, or a range of an archive's buffer.
enum Blob {
    Owned(Vec<u8>),
    Range(Arc<Vec<u8>>, Range<usize>),
}

impl Blob {
    fn bytes(&self) -> &[u8] {
        match self {
            Blob::Owned(v) => v,
            Blob::Range(a, r) => &a[r.clone()],
        }
    }
}

/// `a/./b/../c` → `a/c`; `None` for a path that leaves the root or is absolute (a hostile archive or
/// `transforms.json` cannot name files outside what the user gave).
pub fn normalise(rel: &str) -> Option<String> {
    if rel.starts_with('/') || rel.starts_with('\\') || rel.contains(':') {
        return None;
    }
    let mut parts: Vec<&str> = Vec::new();
    for p in rel.split(['/', '\\']) {
        match p {
            "" | "." => {}
            ".." => {
                parts.pop()?;
            }
            p => parts.push(p),
        }
    }
    (!parts.is_empty()).then(|| parts.join("/"))
}

impl Files {
    pub fn new(name: impl Into<String>) -> Files {
        Files {
            name: name.into(),
            ..Files::default()
        }
    }

    /// Adds a file; paths that leave the root are refused.
    pub fn insert(&mut self, rel: &str, bytes: Vec<u8>) -> Result<(), DatasetError> {
        self.insert_blob(rel, Blob::Owned(bytes))?;
        self.archive = None;
        Ok(())
    }

    fn insert_blob(&mut self, rel: &str, blob: Blob) -> Result<(), DatasetError> {
        let key = normalise(rel).ok_or_else(|| DatasetError::Format {
            path: PathBuf::from(format!("{}:{rel}", self.name)),
            detail: "the path leaves the dataset (absolute, or `..` above its root)".into(),
        })?;
        self.files.insert(key, blob);
        Ok(())
    }

    pub fn len(&self) -> usize {
        self.files.len()
    }

    pub fn is_empty(&self) -> bool {
        self.files.is_empty()
    }

    /// Total bytes held.
    pub fn bytes(&self) -> u64 {
        self.files.values().map(|v| v.bytes().len() as u64).sum()
    }

    /// The file names, sorted.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.files.keys().map(String::as_str)
    }

    /// Re-roots at the folder holding the shallowest `transforms.json` (a dropped folder arrives as
    /// `capture/transforms.json`, an archive may hold one top folder); files outside it are dropped.
    pub fn rooted_at_transforms(mut self) -> Result<Files, DatasetError> {
        let best = self
            .files
            .keys()
            .filter(|k| *k == "transforms.json" || k.ends_with("/transforms.json"))
            .min_by_key(|k| (k.matches('/').count(), k.len()))
            .cloned()
            .ok_or_else(|| DatasetError::Format {
                path: PathBuf::from(&self.name),
                detail: format!(
                    "no transforms.json among its {} files (a dataset folder as DATASET.md describes, a nerfstudio folder, or an archive from `silvr pack`)",
                    self.files.len()
                ),
            })?;
        let prefix = &best[..best.len() - "transforms.json".len()];
        if prefix.is_empty() {
            return Ok(self);
        }
        let prefix = prefix.to_string();
        let files = std::mem::take(&mut self.files)
            .into_iter()
            .filter_map(|(k, v)| k.strip_prefix(&prefix).map(|r| (r.to_string(), v)))
            .collect();
        Ok(Files {
            name: format!("{}/{}", self.name, prefix.trim_end_matches('/')),
            files,
            archive: self.archive,
        })
    }

    /// Reads a tar archive (`silvr pack`'s format; any POSIX/GNU tar of a dataset folder) without copying
    /// it: the headers are parsed once and each regular file is kept as a range of `bytes`. Links and
    /// devices are ignored; an entry whose declared size runs past the end of the archive is refused
    /// before anything is allocated for it, and so is an archive over [`MAX_BYTES`].
    pub fn from_tar(name: &str, bytes: Vec<u8>) -> Result<Files, DatasetError> {
        let bad = |detail: String| DatasetError::Format {
            path: PathBuf::from(name),
            detail,
        };
        if bytes.len() as u64 > MAX_BYTES {
            return Err(bad(format!(
                "{} bytes is more than the {} GiB the studio reads",
                bytes.len(),
                MAX_BYTES >> 30
            )));
        }
        if bytes.len() < 512 {
            return Err(bad("too short to be a tar archive".into()));
        }
        let len = bytes.len() as u64;
        let mut ranges = Vec::new();
        {
            // Seeking over each entry's data: only headers (and GNU long names / PAX records, which
            // are bounded by the bytes present) are read.
            let mut archive = tar::Archive::new(std::io::Cursor::new(bytes.as_slice()));
            let entries = archive
                .entries_with_seek()
                .map_err(|e| bad(format!("not a tar archive: {e}")))?;
            for entry in entries {
                let entry = entry.map_err(|e| bad(format!("corrupt tar archive: {e}")))?;
                if !entry.header().entry_type().is_file() {
                    continue;
                }
                let path = entry
                    .path()
                    .map_err(|e| bad(format!("an entry's name is unreadable: {e}")))?
                    .to_string_lossy()
                    .into_owned();
                let (at, size) = (entry.raw_file_position(), entry.size());
                let left = len.saturating_sub(at);
                if size > left {
                    return Err(bad(format!(
                        "{path}: says it holds {size} bytes, but only {left} bytes of the archive follow \
                         (truncated or corrupt)"
                    )));
                }
                // Both fit in usize: they are within the buffer's length.
                ranges.push((path, at as usize..(at + size) as usize));
            }
        }
        let archive = Arc::new(bytes);
        let mut out = Files::new(name);
        for (path, range) in ranges {
            out.insert_blob(&path, Blob::Range(archive.clone(), range))?;
        }
        if out.is_empty() {
            return Err(bad("the archive holds no files".into()));
        }
        out.archive = Some(archive);
        Ok(out)
    }

    /// A tar archive of these files: the one they were read from, when they were ([`Self::from_tar`],
    /// maybe re-rooted: it may then hold more, which re-rooting drops again), without a copy; else a
    /// new one ([`Self::to_tar`]).
    pub fn as_tar(&self) -> Cow<'_, [u8]> {
        match &self.archive {
            Some(a) => Cow::Borrowed(a.as_slice()),
            None => Cow::Owned(self.to_tar()),
        }
    }

    /// Writes these files as a tar archive (sorted names, fixed times and modes: the same files give the
    /// same bytes).
    pub fn to_tar(&self) -> Vec<u8> {
        let mut b = tar::Builder::new(Vec::new());
        b.mode(tar::HeaderMode::Deterministic);
        for (k, v) in &self.files {
            let v = v.bytes();
            let mut h = tar::Header::new_gnu();
            h.set_size(v.len() as u64);
            h.set_mode(0o644);
            h.set_mtime(0);
            h.set_entry_type(tar::EntryType::Regular);
            b.append_data(&mut h, k, v)
                .expect("appending to an in-memory tar cannot fail");
        }
        b.into_inner()
            .expect("finishing an in-memory tar cannot fail")
    }
}

impl Source for Files {
    fn read(&self, rel: &str) -> Result<Cow<'_, [u8]>, DatasetError> {
        normalise(rel)
            .and_then(|k| self.files.get(&k))
            .map(|v| Cow::Borrowed(v.bytes()))
            .ok_or_else(|| DatasetError::Format {
                path: self.path(rel),
                detail: "missing".into(),
            })
    }

    fn exists(&self, rel: &str) -> bool {
        normalise(rel).is_some_and(|k| self.files.contains_key(&k))
    }

    fn path(&self, rel: &str) -> PathBuf {
        PathBuf::from(format!("{}:{rel}", self.name))
    }

    fn root(&self) -> PathBuf {
        PathBuf::from(&self.name)
    }
}

/// Opens what a user names: a dataset folder, its `transforms.json`, or a `silvr pack` archive (`.tar`).
/// Returns the source and the name of the transforms file within it. A folder is confined to itself.
pub fn open(path: &Path) -> Result<(Box<dyn Source>, String), DatasetError> {
    open_within(path, None)
}

/// [`open`], with the names of a folder's transforms file allowed to reach anything under `root` (an
/// ancestor of the folder; `None`: the folder itself). An archive is always confined to itself.
pub fn open_within(
    path: &Path,
    root: Option<&Path>,
) -> Result<(Box<dyn Source>, String), DatasetError> {
    let dir = |folder: &Path| -> Result<Box<dyn Source>, DatasetError> {
        Ok(Box::new(match root {
            Some(root) => Dir::within(folder, root)?,
            None => Dir::new(folder),
        }))
    };
    if path.is_dir() {
        return Ok((dir(path)?, "transforms.json".into()));
    }
    let is_tar = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("tar"));
    if is_tar {
        let bytes = read_bounded(path, MAX_BYTES)?;
        let files = Files::from_tar(&path.display().to_string(), bytes)?.rooted_at_transforms()?;
        return Ok((Box::new(files), "transforms.json".into()));
    }
    let folder = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "transforms.json".into());
    Ok((dir(folder)?, name))
}

/// The bytes of the regular file `path`, refused before reading when it is not a regular file (a FIFO or
/// a device would block or never end) or holds more than `max` bytes; the buffer is reserved fallibly.
pub fn read_bounded(path: &Path, max: u64) -> Result<Vec<u8>, DatasetError> {
    use std::io::Read;
    let io = |source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    };
    let bad = |detail: String| DatasetError::Format {
        path: path.to_path_buf(),
        detail,
    };
    // Before `open`: opening a FIFO blocks until someone writes to it.
    if !std::fs::metadata(path).map_err(io)?.is_file() {
        return Err(bad("not a regular file".into()));
    }
    let f = std::fs::File::open(path).map_err(io)?;
    let meta = f.metadata().map_err(io)?;
    if !meta.is_file() {
        return Err(bad("not a regular file".into()));
    }
    if meta.len() > max {
        return Err(bad(format!(
            "{} bytes is more than the {max} bytes read from one file",
            meta.len()
        )));
    }
    let mut bytes = Vec::new();
    bytes
        .try_reserve_exact(meta.len() as usize)
        .map_err(|_| bad(format!("{} bytes do not fit in memory", meta.len())))?;
    // A file that grows while it is read stops at the bound all the same.
    f.take(max + 1).read_to_end(&mut bytes).map_err(io)?;
    if bytes.len() as u64 > max {
        return Err(bad(format!("grew beyond {max} bytes while it was read")));
    }
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_that_leave_the_root_are_refused() {
        assert_eq!(normalise("./a/b/../c.png").as_deref(), Some("a/c.png"));
        assert_eq!(normalise("a\\b.png").as_deref(), Some("a/b.png"));
        for bad in ["../x", "/etc/passwd", "a/../../x", "C:/x", "", "."] {
            assert_eq!(normalise(bad), None, "{bad}");
        }
        let mut f = Files::new("drop");
        assert!(f.insert("../../etc/passwd", vec![1]).is_err());
        assert!(f.is_empty());
    }

    /// A folder refuses what `Files` refuses, and what only a disk has: symbolic links out of the root,
    /// FIFOs and devices. A wider root lets `..` reach a sibling folder, and no further.
    #[cfg(unix)]
    #[test]
    fn folders_refuse_paths_that_leave_the_root() {
        let tmp = tempfile::tempdir().unwrap();
        let world = tmp.path().join("world");
        let data = world.join("dataset");
        std::fs::create_dir_all(data.join("images")).unwrap();
        std::fs::write(data.join("images/a.png"), b"png").unwrap();
        std::fs::write(world.join("secret"), b"outside").unwrap();
        std::fs::write(tmp.path().join("far"), b"outside").unwrap();
        std::os::unix::fs::symlink(world.join("secret"), data.join("images/link.png")).unwrap();
        std::os::unix::fs::symlink("a.png", data.join("images/inner.png")).unwrap();
        let fifo = data.join("images/fifo.png");
        assert!(std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap()
            .success());

        let dir = Dir::new(&data);
        assert_eq!(dir.read("images/a.png").unwrap().as_ref(), b"png");
        assert_eq!(
            dir.read("./images/../images/inner.png").unwrap().as_ref(),
            b"png"
        );
        for (rel, why) in [
            ("../secret", "leaves the dataset's root"),
            ("images/../../secret", "leaves the dataset's root"),
            ("/etc/passwd", "leaves the dataset's root"),
            (
                world.join("secret").to_str().unwrap(),
                "leaves the dataset's root",
            ),
            ("images/link.png", "symbolic link leads outside"),
            ("images/fifo.png", "not a regular file"),
        ] {
            let e = dir.read(rel).unwrap_err().to_string();
            assert!(e.contains(why), "{rel}: {e}");
            assert!(
                e.contains(&data.join(rel).display().to_string()),
                "{rel}: {e}"
            );
            // Refused, not missing: the loader reads it and says why instead of skipping the frame.
            assert!(dir.exists(rel), "{rel}");
        }
        assert!(!dir.exists("images/b.png"));

        // Within `world`: a sibling file is in reach, what lies above `world` is not.
        let wide = Dir::within(&data, &world).unwrap();
        assert_eq!(wide.read("../secret").unwrap().as_ref(), b"outside");
        assert_eq!(wide.read("images/link.png").unwrap().as_ref(), b"outside");
        let e = wide.read("../../far").unwrap_err().to_string();
        assert!(e.contains("leaves the dataset's root"), "{e}");
        assert!(
            Dir::within(&world, &data).is_err(),
            "a root below the folder"
        );
    }

    /// An entry that claims more than the archive holds is refused before anything is reserved for it.
    #[test]
    fn a_tar_entry_larger_than_the_archive_is_refused() {
        let mut h = tar::Header::new_gnu();
        h.set_path("transforms.json").unwrap();
        h.set_size(10 << 30);
        h.set_entry_type(tar::EntryType::Regular);
        h.set_cksum();
        let mut bytes = h.as_bytes().to_vec();
        bytes.resize(2048, 0);
        let e = Files::from_tar("big.tar", bytes).err().unwrap().to_string();
        assert!(
            e.starts_with("big.tar: transforms.json: says it holds 10737418240 bytes"),
            "{e}"
        );
        // Files added after reading are written into a new archive.
        let mut f = Files::new("d");
        f.insert("a", vec![1; 10]).unwrap();
        let mut back = Files::from_tar("d.tar", f.to_tar()).unwrap();
        back.insert("b", vec![2]).unwrap();
        assert!(matches!(back.as_tar(), Cow::Owned(_)));
        assert_eq!(
            Files::from_tar("e.tar", back.as_tar().into_owned())
                .unwrap()
                .len(),
            2
        );
    }

    #[test]
    fn tar_round_trip_and_re_rooting() {
        let mut f = Files::new("capture");
        f.insert("capture/transforms.json", b"{}".to_vec()).unwrap();
        f.insert("capture/images/a.png", vec![7; 1000]).unwrap();
        f.insert("other/x", vec![1]).unwrap();
        let tar = f.to_tar();
        assert_eq!(tar, f.to_tar(), "deterministic");
        let back = Files::from_tar("s.tar", tar.clone()).unwrap();
        // The archive is kept as it was read, not copied per file nor rebuilt.
        assert_eq!(back.as_tar().as_ref(), tar.as_slice());
        assert!(matches!(back.as_tar(), Cow::Borrowed(_)));
        assert_eq!(back.len(), 3);
        let r = back.rooted_at_transforms().unwrap();
        assert_eq!(r.len(), 2);
        assert_eq!(r.read("images/a.png").unwrap().len(), 1000);
        assert!(r.exists("./transforms.json"));
        assert!(!r.exists("x"));
        assert_eq!(
            r.path("images/b.png"),
            PathBuf::from("s.tar/capture:images/b.png")
        );
        let e = r.read("images/b.png").unwrap_err().to_string();
        assert!(
            e.contains("s.tar/capture:images/b.png") && e.contains("missing"),
            "{e}"
        );
    }

    #[test]
    fn corrupt_archives_are_errors_naming_the_archive() {
        let mut f = Files::new("d");
        f.insert("transforms.json", vec![b'x'; 3000]).unwrap();
        let tar = f.to_tar();
        for (what, bytes) in [
            ("short", tar[..100].to_vec()),
            ("truncated", tar[..1500].to_vec()),
            ("garbage", vec![0xAB; 4096]),
        ] {
            let e = Files::from_tar("bad.tar", bytes);
            let e = match e {
                Ok(files) => files.rooted_at_transforms().err().map(|e| e.to_string()),
                Err(e) => Some(e.to_string()),
            };
            let e = e.unwrap_or_else(|| panic!("{what}: accepted"));
            assert!(e.contains("bad.tar"), "{what}: {e}");
        }
        let e = Files::new("empty")
            .rooted_at_transforms()
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("no transforms.json"), "{e}");
    }
}
