//! PCL PCD clouds (ascii, binary, binary_compressed with LZF).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = silvr_core::ingest::pcd::read_pcd_bytes(data, "fuzz.pcd");
});
