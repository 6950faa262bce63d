//! Where a dataset's files come from. Natively a folder; in the studio's worker the files a user dropped,
//! an archive written by `silvr pack`, or files fetched over HTTP. The loader (`train::data`) reads through
//! [`Source`] only, so the native binary and the browser share one loader and one set of errors, each
//! naming the file as the user knows it (`dataset/images/0001.png`, `submap.tar:images/0001.png`).
//!
//! The archive is a plain POSIX tar (no compression: the images are PNG or JPEG already), so a user can
//! inspect or unpack it with `tar tf` / `tar xf`.

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::dataset::DatasetError;

/// Largest archive or set of dropped files the studio reads (the browser holds them in memory).
pub const MAX_BYTES: u64 = 3 << 30;

/// A dataset's files, named by `/`-separated paths relative to the dataset root.
pub trait Source: Sync {
    /// The bytes of `rel`.
    fn read(&self, rel: &str) -> Result<Cow<'_, [u8]>, DatasetError>;
    /// Whether `rel` exists (and is a file).
    fn exists(&self, rel: &str) -> bool;
    /// How messages name `rel`.
    fn path(&self, rel: &str) -> PathBuf;
    /// How messages name the whole source (the folder, archive or dropped folder).
    fn root(&self) -> PathBuf;
}

/// A folder on disk. Relative paths are joined as written (a user's own `transforms.json` may point
/// anywhere on their disk, as nerfstudio allows).
pub struct Dir(pub PathBuf);

impl Source for Dir {
    fn read(&self, rel: &str) -> Result<Cow<'_, [u8]>, DatasetError> {
        let p = self.path(rel);
        std::fs::read(&p)
            .map(Cow::Owned)
            .map_err(|source| DatasetError::Io { path: p, source })
    }

    fn exists(&self, rel: &str) -> bool {
        self.path(rel).is_file()
    }

    fn path(&self, rel: &str) -> PathBuf {
        self.0.join(rel)
    }

    fn root(&self) -> PathBuf {
        self.0.clone()
    }
}

/// Files held in memory: an unpacked archive, or the files of a dropped folder.
#[derive(Default)]
pub struct Files {
    /// The archive's or folder's name, for messages.
    pub name: String,
    files: BTreeMap<String, Vec<u8>>,
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
            files: BTreeMap::new(),
        }
    }

    /// Adds a file; paths that leave the root are refused.
    pub fn insert(&mut self, rel: &str, bytes: Vec<u8>) -> Result<(), DatasetError> {
        let key = normalise(rel).ok_or_else(|| DatasetError::Format {
            path: PathBuf::from(format!("{}:{rel}", self.name)),
            detail: "the path leaves the dataset (absolute, or `..` above its root)".into(),
        })?;
        self.files.insert(key, bytes);
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
        self.files.values().map(|v| v.len() as u64).sum()
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
        })
    }

    /// Unpacks a tar archive (`silvr pack`'s format; any POSIX/GNU tar of a dataset folder). Only regular
    /// files are kept; links and devices are ignored; every size is checked against what the archive holds.
    pub fn from_tar(name: &str, bytes: &[u8]) -> Result<Files, DatasetError> {
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
        let mut out = Files::new(name);
        let mut archive = tar::Archive::new(std::io::Cursor::new(bytes));
        let entries = archive
            .entries()
            .map_err(|e| bad(format!("not a tar archive: {e}")))?;
        for entry in entries {
            let mut entry = entry.map_err(|e| bad(format!("corrupt tar archive: {e}")))?;
            if !entry.header().entry_type().is_file() {
                continue;
            }
            let path = entry
                .path()
                .map_err(|e| bad(format!("an entry's name is unreadable: {e}")))?
                .to_string_lossy()
                .into_owned();
            let size = entry.size();
            if size > bytes.len() as u64 {
                return Err(bad(format!(
                    "{path}: says it holds {size} bytes, more than the whole archive"
                )));
            }
            let mut data = Vec::with_capacity(size as usize);
            std::io::Read::read_to_end(&mut entry, &mut data)
                .map_err(|e| bad(format!("{path}: cannot be read: {e}")))?;
            if data.len() as u64 != size {
                return Err(bad(format!(
                    "{path}: truncated ({} of {size} bytes)",
                    data.len()
                )));
            }
            out.insert(&path, data)?;
        }
        if out.is_empty() {
            return Err(bad("the archive holds no files".into()));
        }
        Ok(out)
    }

    /// Writes these files as a tar archive (sorted names, fixed times and modes: the same files give the
    /// same bytes).
    pub fn to_tar(&self) -> Vec<u8> {
        let mut b = tar::Builder::new(Vec::new());
        b.mode(tar::HeaderMode::Deterministic);
        for (k, v) in &self.files {
            let mut h = tar::Header::new_gnu();
            h.set_size(v.len() as u64);
            h.set_mode(0o644);
            h.set_mtime(0);
            h.set_entry_type(tar::EntryType::Regular);
            b.append_data(&mut h, k, v.as_slice())
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
            .map(|v| Cow::Borrowed(v.as_slice()))
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
/// Returns the source and the name of the transforms file within it.
pub fn open(path: &Path) -> Result<(Box<dyn Source>, String), DatasetError> {
    if path.is_dir() {
        return Ok((Box::new(Dir(path.to_path_buf())), "transforms.json".into()));
    }
    let is_tar = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("tar"));
    if is_tar {
        let bytes = std::fs::read(path).map_err(|source| DatasetError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let files = Files::from_tar(&path.display().to_string(), &bytes)?.rooted_at_transforms()?;
        return Ok((Box::new(files), "transforms.json".into()));
    }
    let root = path.parent().unwrap_or(Path::new(".")).to_path_buf();
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "transforms.json".into());
    Ok((Box::new(Dir(root)), name))
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

    #[test]
    fn tar_round_trip_and_re_rooting() {
        let mut f = Files::new("capture");
        f.insert("capture/transforms.json", b"{}".to_vec()).unwrap();
        f.insert("capture/images/a.png", vec![7; 1000]).unwrap();
        f.insert("other/x", vec![1]).unwrap();
        let tar = f.to_tar();
        assert_eq!(tar, f.to_tar(), "deterministic");
        let back = Files::from_tar("s.tar", &tar).unwrap();
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
            let e = Files::from_tar("bad.tar", &bytes);
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
