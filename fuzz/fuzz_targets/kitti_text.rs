//! KITTI's text files (`calib.txt`, `times.txt`): every field checked, errors never panics; the
//! projections and `Tr` a calibration yields are read as `silvr import kitti` reads them.
#![no_main]
use libfuzzer_sys::fuzz_target;
use silvr_core::ingest::kitti;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    if let Ok(c) = kitti::parse_calib(&text, "calib.txt") {
        for key in ["P0", "P2", "P3"] {
            let _ = c.projection(key);
        }
        let _ = c.rigid("Tr");
        let _ = c.rigid_rt("R", "T");
    }
    let _ = kitti::parse_times(&text, "times.txt");
});
