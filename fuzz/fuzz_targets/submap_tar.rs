//! A dropped or fetched submap archive (`silvr pack`'s tar): unpack, re-root at its transforms.json, load
//! it as training data — errors, never a panic or a runaway allocation.
#![no_main]
use libfuzzer_sys::fuzz_target;
use silvr_core::source::Files;
use silvr_core::train::data::{LoadOptions, TrainData};

fuzz_target!(|data: &[u8]| {
    if let Ok(files) = Files::from_tar("fuzz.tar", data.to_vec()).and_then(Files::rooted_at_transforms) {
        let _ = TrainData::load_from(&files, "transforms.json", &LoadOptions::default());
    }
});
