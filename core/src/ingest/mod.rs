//! Real data in: ROS 1 and ROS 2 bags (MCAP, `.db3`, `.bag`), their sensor messages, and PCD clouds.
//!
//! - [`cdr`]: zero-copy CDR cursor (and a writer for tests and our own bags).
//! - [`ros`]: hand-written decoders of the message types the ingest uses, with conversion to points with
//!   per-point time, RGB images and camera models.
//! - [`bag`] (native only): a recording as one stream of messages whatever its container (recognised from
//!   the content), with per-topic summaries; [`mcap`], [`ros1bag`] (ROS 1 format 2.0) and [`rosbag2`]
//!   (`metadata.yaml` + SQLite `.db3` or MCAP) are its containers, over what they share in [`container`].
//! - [`ros1`]: ROS 1 messages rewritten as CDR from the message definitions their bag carries.
//! - [`config`] (native only): the rig file (Oxford Spires `sensor.yaml` + an `ingest:` block).
//! - [`tf`]: static TF tree lookups.
//! - [`rosbag`] (native only): a bag + rig file → the dataset layout (`silvr ingest`).
//! - [`writer`] (native only): writes ROS 2 MCAP bags (the synthetic world as a bag, round-trip tests).
//! - [`convert`] (native only): nerfstudio `transforms.json` → dataset (depth units, z-depth → range);
//!   dataset → COLMAP text model.
//! - [`spires`] (native only): the Oxford Spires folder layout ↔ dataset.
//! - [`npz`]: NumPy `.npy` / `.npz` float arrays (DGP lidar sweeps).
//! - [`dgp`] (native only): a DGP scene folder (TRI / Parallel Domain) → the dataset layout.
//! - [`pcd`]: PCL's PCD (ascii, binary, binary_compressed) into a [`crate::pointcloud::PointCloud`].
//! - [`colmap`]: COLMAP text models (`cameras.txt`, `images.txt`, `points3D.txt`), read and written.
//! - [`poses`]: trajectories from TUM, KITTI odometry, Oxford Spires `slam-poses.csv` and EuRoC `data.csv`
//!   (with format detection), and writers for KITTI and Spires.
//! - [`kitti`]: KITTI velodyne `.bin` scans and nuScenes `.pcd.bin` sweeps (headerless f32 records), and
//!   KITTI's `calib.txt` / `calib_*.txt` and `times.txt`.
//! - [`kitti_import`] (native only): a KITTI odometry sequence → the dataset layout, and its lidar for
//!   lidar odometry.
//! - [`odometry_input`] (native only): the sweeps of a bag or a KITTI sequence in time order, for lidar
//!   odometry (`silvr odometry`), with the sequence's ground truth where it has one.
//!
//! Every reader treats its input as untrusted: errors, never panics, and no allocation larger than the
//! input justifies.

#[cfg(not(target_arch = "wasm32"))]
pub mod bag;
pub mod cdr;
pub mod colmap;
#[cfg(not(target_arch = "wasm32"))]
pub mod config;
#[cfg(not(target_arch = "wasm32"))]
pub mod container;
#[cfg(not(target_arch = "wasm32"))]
pub mod convert;
#[cfg(not(target_arch = "wasm32"))]
pub mod dgp;
pub mod kitti;
#[cfg(not(target_arch = "wasm32"))]
pub mod kitti_import;
#[cfg(not(target_arch = "wasm32"))]
pub mod mcap;
pub mod npz;
#[cfg(not(target_arch = "wasm32"))]
pub mod odometry_input;
pub mod pcd;
pub mod poses;
pub mod ros;
pub mod ros1;
#[cfg(not(target_arch = "wasm32"))]
pub mod ros1bag;
#[cfg(not(target_arch = "wasm32"))]
pub mod rosbag;
#[cfg(not(target_arch = "wasm32"))]
pub mod rosbag2;
#[cfg(not(target_arch = "wasm32"))]
pub mod spires;
pub mod tf;
#[cfg(not(target_arch = "wasm32"))]
pub mod writer;
