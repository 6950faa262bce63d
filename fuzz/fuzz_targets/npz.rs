//! NumPy `.npz` archives (DGP lidar sweeps) and bare `.npy` arrays: checked offsets, inflation bounded by
//! the declared sizes and the cap — errors, never a panic, an overflow or a zip bomb's gigabytes.
#![no_main]
use libfuzzer_sys::fuzz_target;
use silvr_core::ingest::npz;

fuzz_target!(|data: &[u8]| {
    let _ = npz::parse_npz(data, "data", "fuzz.npz");
    let _ = npz::parse_npy(data, "fuzz.npy");
});
