//! nerfstudio transforms.json: parse, then turn every frame into our camera model and pose.
#![no_main]
use libfuzzer_sys::fuzz_target;
use silvr_core::dataset::Transforms;

fuzz_target!(|data: &[u8]| {
    if let Ok(t) = serde_json::from_slice::<Transforms>(data) {
        for f in &t.frames {
            let _ = f.camera(std::path::Path::new("fuzz/transforms.json"));
        }
    }
});
