//! ROS 1 message definitions and messages (`silvr ingest` of ROS 1 bags): the `.msg` text a connection
//! carries is parsed, and a message is rewritten as CDR from it and decoded. Input: the type name, a
//! newline, the definition text, a NUL byte, then the message bytes.
#![no_main]
use libfuzzer_sys::fuzz_target;
use silvr_core::ingest::{ros, ros1::Definition};

fuzz_target!(|data: &[u8]| {
    let split = data.iter().position(|&b| b == 0).unwrap_or(data.len());
    let (text, msg) = (&data[..split], data.get(split + 1..).unwrap_or(&[]));
    let text = String::from_utf8_lossy(text);
    let (ty, def) = text.split_once('\n').unwrap_or(("pkg/Type", &text));
    let Ok(d) = Definition::parse(ty, def) else {
        return;
    };
    if let Ok(cdr) = d.to_cdr(msg) {
        let _ = ros::decode(ty, &cdr);
    }
});
