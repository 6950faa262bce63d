//! Trajectory files: TUM, KITTI (with a times file after the first NUL, or a frame period), Oxford Spires
//! slam-poses.csv, EuRoC data.csv, and the format detection that picks between them.
#![no_main]
use libfuzzer_sys::fuzz_target;
use silvr_core::ingest::poses::{self, KittiTimes};

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let (main, times) = text.split_once('\0').unwrap_or((text, ""));
    let _ = poses::detect_format("fuzz.txt", main);
    let _ = poses::parse_tum(main, "fuzz.txt");
    let _ = poses::parse_spires(main, "slam-poses.csv");
    let _ = poses::parse_euroc(main, "data.csv");
    let _ = poses::parse_kitti(main, "00.txt", KittiTimes::Text { text: times, name: "times.txt" });
    let _ = poses::parse_kitti(main, "00.txt", KittiTimes::Period(0.1));
});
