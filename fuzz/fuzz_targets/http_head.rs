//! `silvr serve`'s request heads (bytes off the network): the head parser, the path a target names and
//! the `Range` header never panic; a path that is accepted is plain segments (no `..`, no separator, no
//! NUL, nothing empty), and a range that is accepted lies inside the file.
#![no_main]
use libfuzzer_sys::fuzz_target;
use silvr::http::{head_end, parse_head, parse_range, request_path, ByteRange};

fuzz_target!(|data: &[u8]| {
    let end = head_end(data);
    if let Some(end) = end {
        assert!(end <= data.len());
    }
    let Ok(req) = parse_head(&data[..end.unwrap_or(data.len())]) else {
        return;
    };
    assert!(!req.method.is_empty() && !req.target.is_empty());
    for (name, _) in &req.headers {
        assert!(!name.is_empty() && !name.bytes().any(|b| b.is_ascii_uppercase()));
    }
    if let Ok(segments) = request_path(&req.target) {
        for s in &segments {
            assert!(!s.is_empty() && s != "." && s != "..", "{segments:?}");
            assert!(!s.contains(['/', '\\', '\0']), "{segments:?}");
        }
    }
    if let Some(value) = req.header("range") {
        for len in [0, 1, 100, u64::MAX] {
            match parse_range(value, len) {
                ByteRange::Part { start, end } => {
                    assert!(start <= end && end < len, "{value:?} of {len}: {start}-{end}")
                }
                ByteRange::Full | ByteRange::Unsatisfiable => {}
            }
        }
    }
});
