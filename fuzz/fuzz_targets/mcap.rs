//! The MCAP container of ROS 2 bags (`silvr ingest`): the streaming reader over bytes in memory, and the
//! CDR decoder of every message of a known type, as `silvr ingest` and the bag summary read them —
//! errors, never a panic (the reader's own panics are caught and reported) or a runaway allocation.
#![no_main]
use libfuzzer_sys::fuzz_target;
use silvr_core::ingest::mcap::BagReader;

fuzz_target!(|data: &[u8]| {
    let reader = BagReader::from_reader(
        "fuzz.mcap",
        std::io::Cursor::new(data.to_vec()),
        data.len() as u64,
    );
    // A bound on the work per input: a few KiB of records cannot hold more messages than this.
    for msg in reader.take(10_000) {
        let Ok(msg) = msg else { break };
        let _ = msg.decode();
    }
});
