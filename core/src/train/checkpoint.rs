//! Checkpoints: everything a resumed run needs to continue bit-for-bit (configuration, step, parameters,
//! Adam moments, loss history), in one file: the magic `SILVRCK1`, a little-endian u64 header length, a
//! JSON header, then the tensors as little-endian f32. Written to a temporary file and renamed.

use std::io::Write;
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::cpu::StepStats;
use super::data::SceneFrame;
use super::TrainConfig;
use crate::field::model::ModelConfig;

const MAGIC: &[u8; 8] = b"SILVRCK1";

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Header {
    pub model: ModelConfig,
    pub config: TrainConfig,
    pub frame: SceneFrame,
    pub step: u32,
    pub adam_t: u32,
    pub names: Vec<String>,
    pub sizes: Vec<usize>,
    pub history: Vec<StepStats>,
}

/// A checkpoint in memory.
pub struct Checkpoint {
    pub header: Header,
    pub params: Vec<Vec<f32>>,
    pub m: Vec<Vec<f32>>,
    pub v: Vec<Vec<f32>>,
}

#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("{path}: {msg}")]
    Bad { path: String, msg: String },
}

fn err(path: &Path, msg: impl Into<String>) -> CheckpointError {
    CheckpointError::Bad {
        path: path.display().to_string(),
        msg: msg.into(),
    }
}

impl Checkpoint {
    pub fn to_bytes(&self) -> Vec<u8> {
        let header = serde_json::to_vec(&self.header).expect("header serialises");
        let words: usize = self.params.iter().map(Vec::len).sum::<usize>() * 3;
        let mut out = Vec::with_capacity(16 + header.len() + words * 4);
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&(header.len() as u64).to_le_bytes());
        out.extend_from_slice(&header);
        for group in [&self.params, &self.m, &self.v] {
            for t in group {
                out.extend_from_slice(bytemuck::cast_slice(t));
            }
        }
        out
    }

    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Checkpoint, CheckpointError> {
        if bytes.len() < 16 || &bytes[..8] != MAGIC {
            return Err(err(path, "not a SiLVR checkpoint (bad magic)"));
        }
        let hl = u64::from_le_bytes(bytes[8..16].try_into().expect("8 bytes")) as usize;
        let body = bytes
            .get(16..16usize.saturating_add(hl))
            .ok_or_else(|| err(path, "truncated header"))?;
        let header: Header =
            serde_json::from_slice(body).map_err(|e| err(path, format!("bad header: {e}")))?;
        let words: usize = header.sizes.iter().sum();
        let data = &bytes[16 + hl..];
        if data.len() != words * 12 {
            return Err(err(
                path,
                format!(
                    "holds {} bytes of tensors, the header describes {}",
                    data.len(),
                    words * 12
                ),
            ));
        }
        let mut off = 0;
        let mut read_group = || {
            header
                .sizes
                .iter()
                .map(|&n| {
                    let t: Vec<f32> = data[off..off + n * 4]
                        .chunks_exact(4)
                        .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
                        .collect();
                    off += n * 4;
                    t
                })
                .collect::<Vec<_>>()
        };
        let params = read_group();
        let m = read_group();
        let v = read_group();
        Ok(Checkpoint {
            header,
            params,
            m,
            v,
        })
    }

    /// Writes atomically (temporary file in the same folder, then rename).
    pub fn save(&self, path: &Path) -> Result<(), CheckpointError> {
        let tmp = path.with_extension("ckpt.partial");
        let mut f = std::fs::File::create(&tmp).map_err(|e| err(&tmp, e.to_string()))?;
        f.write_all(&self.to_bytes())
            .and_then(|_| f.sync_all())
            .map_err(|e| err(&tmp, e.to_string()))?;
        std::fs::rename(&tmp, path).map_err(|e| err(path, e.to_string()))
    }

    pub fn load(path: &Path) -> Result<Checkpoint, CheckpointError> {
        let bytes = std::fs::read(path).map_err(|e| err(path, e.to_string()))?;
        Self::from_bytes(&bytes, path)
    }
}
