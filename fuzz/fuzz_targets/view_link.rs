//! The studio's share links (the URL hash a page opens): never a panic, only fetchable sources and
//! bounded values accepted, and what is accepted survives its own link.
#![no_main]
use libfuzzer_sys::fuzz_target;
use silvr_worker::view::{is_fetchable, ViewState, MAX_SOURCES, POINT_SIZE};

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let (v, _) = ViewState::from_hash(text);
    assert!(v.sources.len() <= MAX_SOURCES);
    assert!(v.sources.iter().all(|s| is_fetchable(s)));
    assert!((POINT_SIZE.0..=POINT_SIZE.1).contains(&v.point_size));
    let (back, notes) = ViewState::from_hash(&v.to_hash());
    assert!(notes.is_empty(), "{notes:?}");
    assert_eq!(back, v);
});
