//! Structure from motion bootstrapped by the SLAM prior (the paper's large-scale pose estimation):
//! `features` (our SIFT), `pairs` (which images to match, from the prior's poses), `matching`
//! (descriptor matching gated by the prior's epipolar geometry), `tracks` (matches chained across
//! images), `triangulate` (points from known poses, COLMAP's filters), `ba` (bundle adjustment with the
//! odometry as prior terms and the rig as a constraint), and `poses`, the stage that runs them in order.

pub mod ba;
pub mod features;
pub mod matching;
pub mod pairs;
pub mod poses;
pub mod tracks;
pub mod triangulate;
