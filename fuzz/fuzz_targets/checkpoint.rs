//! Training checkpoints (`SILVRCK1`: header length, JSON header, f32 tensors): every size in the header is
//! checked against the file and the model before anything is allocated.
#![no_main]
use std::path::Path;

use libfuzzer_sys::fuzz_target;
use silvr_core::train::checkpoint::Checkpoint;

fuzz_target!(|data: &[u8]| {
    if let Ok(ck) = Checkpoint::from_bytes(data, Path::new("fuzz.ckpt")) {
        // What was accepted serialises again.
        let _ = ck.to_bytes();
    }
});
