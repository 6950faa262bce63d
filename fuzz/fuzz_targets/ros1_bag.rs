//! ROS 1 bags (`silvr ingest`): the record and chunk reader over bytes in memory (uncompressed, bz2 and lz4
//! chunks, with or without an index), the message definitions each connection carries, and every message
//! of a known type rewritten as CDR and decoded — errors, never a panic or a runaway allocation.
#![no_main]
use libfuzzer_sys::fuzz_target;
use silvr_core::ingest::bag::BagReader;

fuzz_target!(|data: &[u8]| {
    // Every input is a ROS 1 bag to the reader: the magic is added where the fuzzer did not keep it.
    const MAGIC: &[u8] = b"#ROSBAG V2.0\n";
    let mut bytes = data.to_vec();
    if !bytes.starts_with(MAGIC) {
        bytes.splice(0..0, MAGIC.iter().copied());
    }
    let Ok(reader) = BagReader::from_bytes("fuzz.bag", bytes) else {
        return;
    };
    for msg in reader.take(10_000) {
        let Ok(msg) = msg else { break };
        let _ = msg.decode();
    }
});
