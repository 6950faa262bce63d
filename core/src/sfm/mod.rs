//! Structure from motion bootstrapped by the SLAM prior (the paper's large-scale pose estimation):
//! `features` (our SIFT), `pairs` (which images to match, from the prior's poses), `matching`
//! (descriptor matching gated by the prior's epipolar geometry), `tracks` (matches chained across
//! images), `triangulate` (points from known poses, COLMAP's filters), `ba` (bundle adjustment with the
//! odometry as prior terms and the rig as a constraint), `places` (which images see the same place, from
//! the images alone) and `loops` (revisits verified in 3-D and closed by a pose graph), and `poses`, the
//! stage that runs them in order.

pub mod ba;
pub mod features;
pub mod loops;
pub mod matching;
pub mod pairs;
pub mod places;
pub mod poses;
pub mod tracks;
pub mod triangulate;
