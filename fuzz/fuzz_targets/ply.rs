//! PLY point clouds (ascii and binary, any element and property layout).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = silvr_core::pointcloud::read_ply_bytes(data, "fuzz.ply");
});
