//! The ingest rig file (Oxford Spires sensor.yaml + ingest block), including the camera models it builds.
#![no_main]
use libfuzzer_sys::fuzz_target;
use silvr_core::ingest::config::RigConfig;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(cfg) = RigConfig::parse(text, "fuzz.yaml") {
        for c in &cfg.sensor.cameras {
            let _ = cfg.camera_model(c);
        }
        let _ = cfg.to_yaml();
    }
});
