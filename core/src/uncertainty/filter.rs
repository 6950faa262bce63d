//! The default uncertainty filter, one rule for the native `silvr uncertainty` (`points_filtered.ply`)
//! and the studio's threshold slider, so both keep the same points of the same cloud.
//!
//! Tukey's (inner) fence on the exported points' combined log10 std: drop a point above
//! Q3 + [`FILTER_FENCE`]·(Q3 − Q1), i.e. an outlier of the cloud's own uncertainty distribution. The fence
//! scales with the spread, so it adapts to how many rays the pass used and to the scene's extent without
//! a per-scene constant. (The first rule, median + 0.5 decades, cut well-observed facades on the ci world,
//! 15 % of recall, and too little on the default world.)

/// The property the default filter reads.
pub const FILTER_FIELD: &str = "log_std_combined";

/// Tukey's fence multiplier.
pub const FILTER_FENCE: f32 = 1.5;

/// The default threshold: Q3 + [`FILTER_FENCE`]·IQR over the finite values (nearest-rank quartiles);
/// infinity when there is none.
pub fn default_threshold(values: &[f32]) -> f32 {
    default_threshold_reordering(&mut values.to_vec())
}

/// [`default_threshold`] on values it reorders and drops the non-finite of (no copy: the COPC export's
/// column of 100 M points).
pub fn default_threshold_reordering(v: &mut Vec<f32>) -> f32 {
    v.retain(|x| x.is_finite());
    if v.is_empty() {
        return f32::INFINITY;
    }
    let rank = |f: f64| ((v.len() - 1) as f64 * f).round() as usize;
    let (r1, r3) = (rank(0.25), rank(0.75));
    // Nearest-rank quartiles by selection: the values a full sort would put at those ranks.
    let q3 = *v.select_nth_unstable_by(r3, f32::total_cmp).1;
    let q1 = *v[..=r3].select_nth_unstable_by(r1, f32::total_cmp).1;
    q3 + FILTER_FENCE * (q3 - q1)
}

/// Whether a point with this value is kept at `threshold` (NaN never is).
pub fn keeps(value: f32, threshold: f32) -> bool {
    value <= threshold
}

/// The points of `cloud` whose `field` is kept at `threshold` (all of them when it has no such field).
pub fn filter_cloud(
    cloud: &crate::pointcloud::PointCloud,
    field: &str,
    threshold: f32,
) -> crate::pointcloud::PointCloud {
    let Some(v) = cloud.scalar(field) else {
        return cloud.clone();
    };
    let keep: Vec<usize> = (0..v.len()).filter(|&i| keeps(v[i], threshold)).collect();
    cloud.select(&keep)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An outlier rule: a cloud whose uncertainties are all alike keeps every point, a far tail is cut.
    #[test]
    fn default_threshold_is_tukeys_fence() {
        let mut v: Vec<f32> = (0..=100).map(|i| i as f32).collect();
        v.push(f32::NAN);
        assert_eq!(default_threshold(&v), 75.0 + 1.5 * 50.0);
        let flat = [2.0f32; 10];
        assert_eq!(default_threshold(&flat), 2.0);
        assert_eq!(default_threshold(&[f32::NAN]), f32::INFINITY);
        let mut tail = vec![1.0f32; 95];
        tail.extend([1.2, 1.4, 6.0, 6.0, 6.0]);
        let t = default_threshold(&tail);
        assert!((1.0..6.0).contains(&t), "{t}");
        assert!(keeps(1.0, 1.0) && !keeps(1.1, 1.0) && !keeps(f32::NAN, f32::INFINITY));
    }
}
