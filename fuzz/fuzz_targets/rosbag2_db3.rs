//! rosbag2 `.db3` files (`silvr ingest` of a rosbag2 bag): SQLite's own reading of a hostile database and
//! ours of its rows (topics, types, serialisation formats, message blobs and stamps, the legacy schema
//! without metadata.yaml), then every message of a known type decoded — errors, never a panic.
#![no_main]
use libfuzzer_sys::fuzz_target;
use silvr_core::ingest::bag::BagReader;

fuzz_target!(|data: &[u8]| {
    // SQLite opens a file, not bytes: each input is written to one temporary file per process. Every
    // input is a SQLite file to the reader: the 16-byte magic is restored where the fuzzer changed it
    // (inserting it would shift every page).
    const MAGIC: &[u8; 16] = b"SQLite format 3\0";
    let mut bytes = data.to_vec();
    if bytes.len() >= MAGIC.len() {
        bytes[..MAGIC.len()].copy_from_slice(MAGIC);
    }
    let path = std::env::temp_dir().join(format!("silvr-fuzz-{}.db3", std::process::id()));
    if std::fs::write(&path, &bytes).is_err() {
        return;
    }
    if let Ok(reader) = BagReader::open(&path) {
        for msg in reader.take(10_000) {
            let Ok(msg) = msg else { break };
            let _ = msg.decode();
        }
    }
    let _ = std::fs::remove_file(&path);
});
