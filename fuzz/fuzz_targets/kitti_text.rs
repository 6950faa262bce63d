//! KITTI's text files (`calib.txt`, `times.txt`; the raw release's `calib_*.txt`, `timestamps.txt` and OXTS
//! records): every field checked, errors never panics; the
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
        let _ = c.projection("P_rect_02");
        let _ = c.exactly("R_rect_00", 9, "a rotation");
    }
    let _ = kitti::parse_times(&text, "times.txt");
    let _ = kitti::parse_datetimes(&text, "timestamps.txt");
    if let Ok(o) = kitti::parse_oxts(&text, "0000000000.txt") {
        let _ = kitti::oxts_poses(&[o, o]);
    }
});
