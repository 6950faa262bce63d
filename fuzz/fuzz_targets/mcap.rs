//! The MCAP container of ROS 2 bags (`silvr ingest`): the streaming reader over bytes in memory, and the
//! CDR decoder of every message of a known type, as `silvr ingest` and the bag summary read them —
//! errors, never a panic (the reader's own panics are caught and reported) or a runaway allocation.
#![no_main]
use libfuzzer_sys::fuzz_target;
use silvr_core::ingest::bag::BagReader;

fuzz_target!(|data: &[u8]| {
    // libfuzzer-sys's panic hook aborts on every panic, even one caught: the mcap crate's own overflow
    // on a record longer than its CRC-less chunk (a panic with overflow checks, found by a 10-minute run;
    // core/tests/ingest.rs `inconsistent_record_in_crc_less_chunk_is_an_error`) is caught by `BagReader`
    // and reported, as the product does. The default hook back: a panic that escapes still aborts (the
    // fuzz target's own catch_unwind), a caught one is only printed.
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| drop(std::panic::take_hook()));
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
