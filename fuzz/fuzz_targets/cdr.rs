//! ROS 2 CDR decoders: the first byte picks the message type, the rest is the payload; every decoded
//! message also goes through the conversions the ingest applies (points, RGB, camera model).
#![no_main]
use libfuzzer_sys::fuzz_target;
use silvr_core::ingest::ros::{self, RosMessage, KNOWN_TYPES};

fuzz_target!(|data: &[u8]| {
    let Some((&pick, payload)) = data.split_first() else {
        return;
    };
    let ty = KNOWN_TYPES[pick as usize % KNOWN_TYPES.len()];
    if let Some(Ok(msg)) = ros::decode(ty, payload) {
        match msg {
            RosMessage::PointCloud2(pc) => {
                let _ = pc.to_scan();
            }
            RosMessage::Image(img) => {
                let _ = img.to_rgb();
            }
            RosMessage::CompressedImage(img) => {
                let _ = img.to_rgb();
            }
            RosMessage::CameraInfo(info) => {
                let _ = info.camera_model();
            }
            _ => {}
        }
    }
});
