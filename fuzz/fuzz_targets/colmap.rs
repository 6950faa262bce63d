//! COLMAP text models: the input is split at the first two NUL bytes into cameras.txt, images.txt and
//! points3D.txt; each is parsed alone and then as one model (cross-references checked).
#![no_main]
use libfuzzer_sys::fuzz_target;
use silvr_core::ingest::colmap;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let mut parts = text.splitn(3, '\0');
    let cameras = parts.next().unwrap_or("");
    let images = parts.next().unwrap_or("");
    let points = parts.next().unwrap_or("");
    let _ = colmap::parse_cameras(cameras, "cameras.txt");
    let _ = colmap::parse_images(images, "images.txt");
    let _ = colmap::parse_points3d(points, "points3D.txt");
    if let Ok(model) = colmap::parse_model("fuzz", cameras, images, points) {
        let _ = colmap::write_cameras(&model.cameras);
    }
});
