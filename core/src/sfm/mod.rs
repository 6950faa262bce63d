//! Structure from motion bootstrapped by the SLAM prior (the paper's large-scale pose estimation):
//! `pairs` (which images to match, from the prior's poses). Feature extraction, matching, triangulation and
//! bundle adjustment follow (issue: poses and submaps).

pub mod pairs;
