//! rosbag2 `metadata.yaml` (`silvr ingest` of a rosbag2 folder): the YAML parse of the fields we use —
//! errors, never a panic.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = silvr_core::ingest::rosbag2::parse_metadata(text);
    }
});
