//! Checkpoints: everything a resumed run needs to continue bit-for-bit (configuration, step, parameters,
//! Adam moments, loss history), in one file: the magic `SILVRCK1`, a little-endian u64 header length, a
//! JSON header, then the tensors as little-endian f32. Written to a temporary file and renamed.

use std::io::{Read, Write};
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::cpu::StepStats;
use super::data::SceneFrame;
use super::TrainConfig;
use crate::field::model::ModelConfig;
use crate::gpu::GpuError;

const MAGIC: &[u8; 8] = b"SILVRCK1";

/// The largest checkpoint [`Checkpoint::load`] reads (nerfacto's default model is about 0.25 GB).
pub const MAX_FILE_BYTES: u64 = 8 << 30;

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

    /// Parses and validates a checkpoint. Every size in the header is checked (with checked arithmetic)
    /// against the file's length and the model's own tensor shapes before anything is allocated, so a
    /// crafted or damaged file is an error naming `path`, never a panic or a runaway allocation.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Checkpoint, CheckpointError> {
        let bad = |msg: String| err(path, msg);
        if bytes.len() < MAGIC.len() || &bytes[..MAGIC.len()] != MAGIC {
            return Err(bad("not a SiLVR checkpoint (bad magic)".into()));
        }
        let Some((hl, rest)) = bytes[MAGIC.len()..].split_first_chunk::<8>() else {
            return Err(bad(format!(
                "truncated: {} bytes, the preamble alone is 16",
                bytes.len()
            )));
        };
        let hl = u64::from_le_bytes(*hl);
        let hl = usize::try_from(hl)
            .ok()
            .filter(|&n| n <= rest.len())
            .ok_or_else(|| {
                bad(format!(
                    "header length {hl} exceeds the {} bytes after the preamble (truncated or corrupt)",
                    rest.len()
                ))
            })?;
        let (body, data) = rest.split_at(hl);
        let header: Header =
            serde_json::from_slice(body).map_err(|e| bad(format!("bad header: {e}")))?;
        header.validate(data.len()).map_err(bad)?;
        let mut words = data.chunks_exact(4);
        let mut read_group = |group: &str| -> Result<Vec<Vec<f32>>, CheckpointError> {
            header
                .names
                .iter()
                .zip(&header.sizes)
                .map(|(name, &n)| {
                    let t: Vec<f32> = words
                        .by_ref()
                        .take(n)
                        .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
                        .collect();
                    // `validate` matched the sizes to the data, so the chunks do not run out.
                    debug_assert_eq!(t.len(), n);
                    if let Some((i, x)) = t.iter().enumerate().find(|(_, x)| !x.is_finite()) {
                        return Err(bad(format!(
                            "{group} of tensor {name} hold a non-finite value ({x}) at index {i}"
                        )));
                    }
                    Ok(t)
                })
                .collect()
        };
        let params = read_group("parameters")?;
        let m = read_group("Adam first moments")?;
        let v = read_group("Adam second moments")?;
        for (name, t) in header.names.iter().zip(&v) {
            if let Some((i, x)) = t.iter().enumerate().find(|(_, x)| **x < 0.0) {
                return Err(bad(format!(
                    "Adam second moments of tensor {name} hold a negative value ({x}) at index {i}"
                )));
            }
        }
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

    /// Reads and validates `path`; files above [`MAX_FILE_BYTES`] are refused before they are read.
    pub fn load(path: &Path) -> Result<Checkpoint, CheckpointError> {
        let f = std::fs::File::open(path).map_err(|e| err(path, e.to_string()))?;
        let len = f.metadata().map_err(|e| err(path, e.to_string()))?.len();
        let too_big = |len: u64| {
            err(
                path,
                format!(
                    "{len} bytes: larger than the {} GiB a checkpoint may have (not a checkpoint?)",
                    MAX_FILE_BYTES >> 30
                ),
            )
        };
        if len > MAX_FILE_BYTES {
            return Err(too_big(len));
        }
        let mut bytes = Vec::with_capacity(usize::try_from(len).map_err(|_| too_big(len))?);
        // `take`: a file that grows while being read is still bounded.
        f.take(MAX_FILE_BYTES + 1)
            .read_to_end(&mut bytes)
            .map_err(|e| err(path, e.to_string()))?;
        if bytes.len() as u64 > MAX_FILE_BYTES {
            return Err(too_big(bytes.len() as u64));
        }
        Self::from_bytes(&bytes, path)
    }
}

impl Header {
    /// Checks the header against itself, the model it describes and the `data_len` bytes of tensors
    /// that follow it. Runs before any tensor is allocated.
    fn validate(&self, data_len: usize) -> Result<(), String> {
        if self.names.len() != self.sizes.len() {
            return Err(format!(
                "header lists {} tensor names but {} sizes",
                self.names.len(),
                self.sizes.len()
            ));
        }
        let want = self
            .sizes
            .iter()
            .try_fold(0usize, |a, &n| a.checked_add(n))
            .and_then(|w| w.checked_mul(12))
            .ok_or("tensor sizes in the header overflow (corrupt header)")?;
        if data_len != want {
            return Err(format!(
                "holds {data_len} bytes of tensors, the header describes {want}{}",
                if data_len < want { " (truncated)" } else { "" }
            ));
        }
        // The messages without `GpuError`'s "invalid input for a GPU kernel" prefix.
        let why = |part: &str, e: GpuError| match e {
            GpuError::InvalidInput(m) => format!("{part} configuration: {m}"),
            e => format!("{part} configuration: {e}"),
        };
        self.model.validate().map_err(|e| why("model", e))?;
        self.config.validate().map_err(|e| why("training", e))?;
        let shapes = self.model.tensor_shapes().map_err(|e| why("model", e))?;
        for (i, (name, n)) in shapes.iter().enumerate() {
            match (self.names.get(i), self.sizes.get(i)) {
                (Some(have), Some(size)) if have == name && size == n => {}
                (Some(have), Some(size)) if have == name => {
                    return Err(format!(
                        "tensor {name} has {size} values, the model's has {n}"
                    ))
                }
                (Some(have), _) => {
                    return Err(format!(
                        "tensor {i} is {have}, the model's tensor {i} is {name}"
                    ))
                }
                _ => {
                    return Err(format!(
                        "header lists {} tensors, the model has {}: {name} is missing",
                        self.names.len(),
                        shapes.len()
                    ))
                }
            }
        }
        if let Some(extra) = self.names.get(shapes.len()) {
            return Err(format!(
                "header lists {} tensors, the model has {}: {extra} is not the model's",
                self.names.len(),
                shapes.len()
            ));
        }
        let f = &self.frame;
        if !(f.center.iter().all(|c| c.is_finite()) && f.scale.is_finite() && f.scale > 0.0) {
            return Err(format!(
                "scene frame needs a finite centre and a finite positive scale, got {:?} and {}",
                f.center, f.scale
            ));
        }
        if self.history.len() > self.step as usize {
            return Err(format!(
                "{} loss-history entries for {} steps",
                self.history.len(),
                self.step
            ));
        }
        if self.adam_t > self.step {
            return Err(format!(
                "{} Adam updates for {} steps",
                self.adam_t, self.step
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::model::Params;
    use crate::train::Mode;

    /// `ModelConfig::tiny()` shrunk until its checkpoint is a few KB (the fuzz seeds' model).
    fn small_model() -> ModelConfig {
        let mut m = ModelConfig::tiny();
        m.field.grid.levels = 2;
        m.field.grid.log2_table_size = 3;
        m.field.density_hidden = 4;
        m.field.geo_features = 3;
        m.field.colour_hidden = 4;
        m.field.appearance_dim = 2;
        for p in &mut m.proposals {
            p.grid.levels = 1;
            p.grid.log2_table_size = 3;
            p.hidden = 4;
        }
        m
    }

    /// A valid checkpoint of `model` after `steps` steps, as `Trainer::checkpoint` fills it.
    fn sample(model: ModelConfig, config: TrainConfig, steps: u32) -> Checkpoint {
        let p = Params::init(&model, 7).unwrap();
        let m = p
            .tensors
            .iter()
            .map(|t| t.iter().map(|x| 0.1 * x).collect());
        let v = p.tensors.iter().map(|t| t.iter().map(|x| x * x).collect());
        Checkpoint {
            header: Header {
                model,
                config,
                frame: SceneFrame {
                    center: [1.5, -2.0, 0.25],
                    scale: 0.125,
                },
                step: steps,
                adam_t: steps,
                names: p.names.clone(),
                sizes: p.tensors.iter().map(Vec::len).collect(),
                history: (0..steps)
                    .map(|i| StepStats {
                        loss: 1.0 / (i + 1) as f64,
                        rgb_mse: 0.01,
                        ..Default::default()
                    })
                    .collect(),
            },
            m: m.collect(),
            v: v.collect(),
            params: p.tensors,
        }
    }

    fn small() -> Checkpoint {
        sample(small_model(), TrainConfig::default(), 3)
    }

    const PATH: &str = "some/run.ckpt";

    fn parse(bytes: &[u8]) -> Result<Checkpoint, String> {
        Checkpoint::from_bytes(bytes, Path::new(PATH)).map_err(|e| {
            let s = e.to_string();
            assert!(s.starts_with(PATH), "the error names the file: {s}");
            s
        })
    }

    fn refused(bytes: &[u8]) -> String {
        match parse(bytes) {
            Ok(_) => panic!("accepted a bad checkpoint"),
            Err(e) => e,
        }
    }

    /// Magic, header length, `header` (any JSON) and the tensor bytes `data`.
    fn encode(header: &serde_json::Value, data: &[u8]) -> Vec<u8> {
        let h = serde_json::to_vec(header).unwrap();
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&(h.len() as u64).to_le_bytes());
        out.extend_from_slice(&h);
        out.extend_from_slice(data);
        out
    }

    /// The header as JSON and the tensor bytes of `ck`.
    fn split(ck: &Checkpoint) -> (serde_json::Value, Vec<u8>) {
        let bytes = ck.to_bytes();
        let hl = u64::from_le_bytes(bytes[8..16].try_into().unwrap()) as usize;
        (
            serde_json::from_slice(&bytes[16..16 + hl]).unwrap(),
            bytes[16 + hl..].to_vec(),
        )
    }

    fn assert_same(a: &Checkpoint, b: &Checkpoint) {
        assert_eq!(a.header.model, b.header.model);
        assert_eq!(a.header.config, b.header.config);
        assert_eq!(a.header.frame, b.header.frame);
        assert_eq!(
            (a.header.step, a.header.adam_t),
            (b.header.step, b.header.adam_t)
        );
        assert_eq!(a.header.names, b.header.names);
        assert_eq!(a.header.sizes, b.header.sizes);
        assert_eq!(a.header.history, b.header.history);
        assert_eq!(a.params, b.params);
        assert_eq!(a.m, b.m);
        assert_eq!(a.v, b.v);
    }

    #[test]
    fn a_valid_checkpoint_round_trips() {
        for ck in [
            small(),
            sample(ModelConfig::tiny(), TrainConfig::default(), 5),
        ] {
            assert_same(&ck, &parse(&ck.to_bytes()).unwrap());
        }
        let tmp = tempfile::tempdir().unwrap();
        let p = tmp.path().join("run.ckpt");
        let ck = small();
        ck.save(&p).unwrap();
        assert_same(&ck, &Checkpoint::load(&p).unwrap());
    }

    #[test]
    fn every_truncation_and_an_extra_byte_are_errors() {
        let bytes = small().to_bytes();
        assert!(bytes.len() < 16 << 10, "{} bytes", bytes.len());
        for n in 0..bytes.len() {
            refused(&bytes[..n]);
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(refused(&longer).contains("bytes of tensors"));
        // A cut in the tensors says so.
        assert!(refused(&bytes[..bytes.len() - 4]).contains("truncated"));
    }

    #[test]
    fn a_header_length_beyond_the_file_is_an_error() {
        let mut bytes = small().to_bytes();
        for hl in [u64::MAX, u64::MAX - 15, 1 << 63, bytes.len() as u64] {
            bytes[8..16].copy_from_slice(&hl.to_le_bytes());
            let e = refused(&bytes);
            assert!(e.contains("header length"), "{e}");
        }
        assert!(refused(b"NOTACKPT........").contains("bad magic"));
    }

    #[test]
    fn sizes_that_overflow_are_errors() {
        let (mut h, data) = split(&small());
        let names = h["names"].clone();
        for sizes in [
            vec![usize::MAX, 2],
            vec![usize::MAX / 2 + 1, usize::MAX / 2 + 1],
            // The sum fits, × 12 does not.
            vec![usize::MAX / 12 + 1],
            vec![usize::MAX / 24 + 1, usize::MAX / 24 + 1],
        ] {
            h["names"] = serde_json::json!(vec!["t"; sizes.len()]);
            h["sizes"] = serde_json::json!(sizes);
            let e = refused(&encode(&h, &data));
            assert!(e.contains("overflow"), "{e}");
        }
        // A sum that fits but claims far more than the file holds.
        h["names"] = names;
        h["sizes"] = serde_json::json!([1u64 << 40, 0, 0, 0, 0, 0, 0, 0]);
        assert!(refused(&encode(&h, &data)).contains("bytes of tensors"));
    }

    #[test]
    fn sizes_or_names_that_disagree_with_the_model_are_errors() {
        let ck = small();
        let (h0, data) = split(&ck);
        let n1 = ck.header.sizes[1];
        // field.density one value short, the data shortened to match: the sizes agree with the file,
        // not with the model.
        let mut h = h0.clone();
        h["sizes"][1] = serde_json::json!(n1 - 1);
        let e = refused(&encode(&h, &data[..data.len() - 12]));
        assert!(
            e.contains("field.density") && e.contains(&n1.to_string()),
            "{e}"
        );
        // Two tensors' sizes swapped: the total is right, the layout is not.
        let mut h = h0.clone();
        let (a, b) = (h["sizes"][0].clone(), h["sizes"][1].clone());
        h["sizes"][0] = b;
        h["sizes"][1] = a;
        assert!(refused(&encode(&h, &data)).contains("field.grid"));
        // A renamed tensor.
        let mut h = h0.clone();
        h["names"][2] = serde_json::json!("field.color");
        assert!(refused(&encode(&h, &data)).contains("field.colour"));
        // Names and sizes of different lengths.
        let mut h = h0.clone();
        h["names"].as_array_mut().unwrap().pop();
        assert!(refused(&encode(&h, &data)).contains("names"));
        // A tensor missing (its bytes too) and one too many.
        let last = *ck.header.sizes.last().unwrap();
        let mut h = h0.clone();
        h["names"].as_array_mut().unwrap().pop();
        h["sizes"].as_array_mut().unwrap().pop();
        let cut = data.len() - last * 12;
        assert!(refused(&encode(&h, &data[..cut])).contains("proposal1.mlp"));
        let mut h = h0.clone();
        h["names"].as_array_mut().unwrap().push("extra".into());
        h["sizes"].as_array_mut().unwrap().push(1.into());
        let mut more = data.clone();
        more.extend_from_slice(&[0; 12]);
        assert!(refused(&encode(&h, &more)).contains("extra"));
    }

    #[test]
    fn absurd_models_are_errors_not_panics_or_allocations() {
        let (h0, data) = split(&small());
        let cases: [(&str, serde_json::Value); 7] = [
            ("/field/grid/log2_table_size", 40.into()),
            ("/field/grid/levels", u32::MAX.into()),
            ("/field/grid/finest_resolution", u32::MAX.into()),
            ("/field/geo_features", u64::MAX.into()),
            ("/field/appearance_dim", u64::MAX.into()),
            ("/images", u64::MAX.into()),
            ("/sampler/samples", 0.into()),
        ];
        for (ptr, value) in cases {
            let mut h = h0.clone();
            *h["model"].pointer_mut(ptr).unwrap() = value;
            let e = refused(&encode(&h, &data));
            assert!(e.contains("model"), "{ptr}: {e}");
        }
        // A 2^30-entry grid the header's sizes agree with is still refused: the file does not hold it.
        let mut h = h0.clone();
        h["model"]["field"]["grid"]["log2_table_size"] = 30.into();
        h["model"]["field"]["grid"]["finest_resolution"] = (1u32 << 20).into();
        h["sizes"][0] = (1u64 << 31).into();
        assert!(refused(&encode(&h, &data)).contains("bytes of tensors"));
        let mut h = h0.clone();
        h["config"]["rays_per_batch"] = 0.into();
        assert!(refused(&encode(&h, &data)).contains("training"));
    }

    #[test]
    fn non_finite_or_negative_values_are_errors_naming_the_tensor() {
        let mut ck = small();
        ck.params[2][5] = f32::NAN;
        let e = refused(&ck.to_bytes());
        assert!(
            e.contains("field.colour") && e.contains("non-finite"),
            "{e}"
        );
        let mut ck = small();
        ck.m[0][0] = f32::INFINITY;
        let e = refused(&ck.to_bytes());
        assert!(
            e.contains("field.grid") && e.contains("first moments"),
            "{e}"
        );
        let mut ck = small();
        ck.v[4][1] = -1.0;
        let e = refused(&ck.to_bytes());
        assert!(
            e.contains("proposal0.grid") && e.contains("negative"),
            "{e}"
        );
    }

    #[test]
    fn history_and_frame_are_checked() {
        let (h0, data) = split(&small());
        let mut h = h0.clone();
        h["step"] = 2.into();
        h["adam_t"] = 2.into();
        assert!(refused(&encode(&h, &data)).contains("history"));
        let mut h = h0.clone();
        h["adam_t"] = 4.into();
        assert!(refused(&encode(&h, &data)).contains("Adam updates"));
        let mut h = h0.clone();
        h["frame"]["scale"] = 0.0.into();
        assert!(refused(&encode(&h, &data)).contains("scene frame"));
        // Fewer history entries than steps is fine.
        let mut h = h0.clone();
        h["history"].as_array_mut().unwrap().pop();
        parse(&encode(&h, &data)).unwrap();
    }

    #[test]
    fn load_refuses_a_huge_file_before_reading_it() {
        let tmp = tempfile::tempdir().unwrap();
        let p = tmp.path().join("huge.ckpt");
        // Sparse: no disk space used, nothing is read.
        std::fs::File::create(&p)
            .unwrap()
            .set_len(MAX_FILE_BYTES + 1)
            .unwrap();
        let e = Checkpoint::load(&p).err().unwrap().to_string();
        assert!(e.contains("huge.ckpt") && e.contains("8 GiB"), "{e}");
        let e = Checkpoint::load(&tmp.path().join("missing.ckpt"))
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("missing.ckpt"), "{e}");
    }

    fn seeds() -> Vec<(&'static str, Checkpoint)> {
        let mut vision = small_model();
        vision.proposals.truncate(1);
        vision.sampler.proposal_samples.truncate(1);
        vision.field.appearance_dim = 0;
        let config = TrainConfig {
            mode: Mode::Vision,
            ..TrainConfig::default()
        };
        vec![
            ("small.ckpt", small()),
            ("vision.ckpt", sample(vision, config, 0)),
        ]
    }

    fn seed_dir() -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/seeds/checkpoint")
    }

    /// Regenerates the fuzz target's seeds:
    /// `cargo test -p silvr-core --lib write_checkpoint_fuzz_seeds -- --ignored`.
    #[test]
    #[ignore]
    fn write_checkpoint_fuzz_seeds() {
        std::fs::create_dir_all(seed_dir()).unwrap();
        for (name, ck) in seeds() {
            std::fs::write(seed_dir().join(name), ck.to_bytes()).unwrap();
        }
    }

    #[test]
    fn the_fuzz_seeds_are_current_valid_checkpoints() {
        for (name, ck) in seeds() {
            let bytes = std::fs::read(seed_dir().join(name)).unwrap();
            assert!(bytes.len() < 200 << 10, "{name}: {} bytes", bytes.len());
            assert_same(&ck, &parse(&bytes).unwrap());
        }
    }
}
