//! KITTI / nuScenes lidar .bin scans (the first byte picks the stride, 4 or 5 floats a point).
#![no_main]
use libfuzzer_sys::fuzz_target;
use silvr_core::ingest::kitti;

fuzz_target!(|data: &[u8]| {
    let Some((&pick, bytes)) = data.split_first() else {
        return;
    };
    let stride = if pick & 1 == 0 { kitti::KITTI_STRIDE } else { kitti::NUSCENES_STRIDE };
    let _ = kitti::read_bin_bytes(bytes, "fuzz.bin", stride);
});
