//! Lidar processing: from raw sweeps to the per-camera supervision the radiance field trains on.
//! The same code serves the synthetic world and real data: [`deskew`] to the image time, [`normals`] by
//! Newell's method on the range image, [`project`] into each camera with the GPU z-buffer, [`images`]
//! encodes depth and normal PNGs, and [`sky`] derives sky masks from lidar no-returns and the image;
//! [`products`] runs them for one keyframe (the synthetic generator and the bag ingest both call it).

pub mod deskew;
pub mod images;
pub mod map;
pub mod normals;
pub mod products;
pub mod project;
pub mod sky;
