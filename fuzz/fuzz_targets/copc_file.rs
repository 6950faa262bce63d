//! COPC as the studio reads it by byte ranges (a shared link or a dropped file): the head (LAS header,
//! VLRs, COPC info, LASzip items, extra-bytes descriptors, our summary), the hierarchy pages and each
//! node's LAZ chunk — errors naming the source, never a panic or a runaway allocation.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    // As in scan_file: the laz decoder's own panics on corrupt chunks are caught and reported natively by
    // `decode_node`; a silent hook keeps the caught ones from printing (an escaping panic still aborts).
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| std::panic::set_hook(Box::new(|_| {})));
    let _ = silvr_core::copc::read::read_bytes(data, "fuzz.copc.laz");
});
