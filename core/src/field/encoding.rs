//! The fixed (parameter-free) parts of nerfacto's field: L∞ scene contraction, the spherical-harmonic view
//! encoding and the truncated exponential density activation. The WGSL twins live in `shaders/field.wgsl`.

/// L∞ scene contraction (mip-NeRF 360 with the max norm, nerfstudio's `SceneContraction(order=inf)`):
/// x inside the unit cube stays, outside it maps to (2 − 1/‖x‖∞)·x/‖x‖∞, so all of space fits [−2, 2]³;
/// then (x + 2)/4 puts it in [0, 1]³, the hash grid's domain. Non-finite input maps to the cube's centre
/// (the caller has already refused non-finite rays; this keeps a stray NaN from indexing the grid).
pub fn contract_unit(x: [f32; 3]) -> [f32; 3] {
    let m = x[0].abs().max(x[1].abs()).max(x[2].abs());
    if !(m.is_finite() && x.iter().all(|v| v.is_finite())) {
        return [0.5; 3];
    }
    let k = if m <= 1.0 { 1.0 } else { (2.0 - 1.0 / m) / m };
    x.map(|v| (v * k + 2.0) * 0.25)
}

/// Degree-4 real spherical harmonics (16 coefficients) of a unit direction, as tiny-cuda-nn's
/// `SphericalHarmonics` encoding that nerfacto's colour head uses.
pub fn sh4(d: [f32; 3]) -> [f32; 16] {
    let [x, y, z] = d;
    let (xx, yy, zz) = (x * x, y * y, z * z);
    let (xy, yz, xz) = (x * y, y * z, x * z);
    [
        0.282_094_8,
        -0.488_602_52 * y,
        0.488_602_52 * z,
        -0.488_602_52 * x,
        1.092_548_5 * xy,
        -1.092_548_5 * yz,
        0.946_174_7 * zz - 0.315_391_57,
        -1.092_548_5 * xz,
        0.546_274_24 * (xx - yy),
        0.590_043_6 * y * (-3.0 * xx + yy),
        2.890_611_4 * xy * z,
        0.457_045_8 * y * (1.0 - 5.0 * zz),
        0.373_176_33 * z * (5.0 * zz - 3.0),
        0.457_045_8 * x * (1.0 - 5.0 * zz),
        1.445_305_7 * z * (xx - yy),
        0.590_043_6 * x * (-xx + 3.0 * yy),
    ]
}

/// Largest logit the density activation passes through (e^15 ≈ 3.3e6 per unit length is opaque at any
/// sample spacing we use): nerfstudio clamps only the gradient; clamping the value too keeps f32 finite.
pub const MAX_LOGIT: f32 = 15.0;

/// trunc_exp: σ = exp(min(logit, 15)); its derivative as nerfstudio's, exp(clamp(logit, −15, 15)).
pub fn trunc_exp(logit: f32) -> (f32, f32) {
    let v = logit.min(MAX_LOGIT).exp();
    let d = logit.clamp(-MAX_LOGIT, MAX_LOGIT).exp();
    (v, d)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn contraction_is_identity_inside_and_bounded_outside() {
        let c = contract_unit([0.5, -0.25, 0.0]);
        assert!((c[0] - 0.625).abs() < 1e-7 && (c[1] - 0.4375).abs() < 1e-7);
        for x in [[10.0, 0.0, 0.0], [1e9, -1e9, 3.0], [-2.0, 1.5, 0.2]] {
            let c = contract_unit(x);
            assert!(c.iter().all(|v| (0.0..=1.0).contains(v)), "{x:?} -> {c:?}");
        }
        // Continuous across the unit cube's face.
        let a = contract_unit([1.0, 0.3, 0.0]);
        let b = contract_unit([1.0 + 1e-4, 0.3, 0.0]);
        assert!((a[0] - b[0]).abs() < 1e-4);
        assert_eq!(contract_unit([f32::NAN, 0.0, 0.0]), [0.5; 3]);
    }

    #[test]
    fn sh_band_energy_is_rotation_invariant() {
        // Σ_m Y_lm² = (2l + 1)/(4π) for every unit direction: checks every constant.
        for d in [
            [0.0, 0.0, 1.0],
            [0.6, 0.0, 0.8],
            [0.48, -0.6, 0.64],
            [-1.0, 0.0, 0.0],
        ] {
            let y = sh4(d);
            let bands = [0..1, 1..4, 4..9, 9..16];
            for (l, r) in bands.into_iter().enumerate() {
                let e: f32 = y[r].iter().map(|v| v * v).sum();
                let want = (2 * l + 1) as f32 / (4.0 * std::f32::consts::PI);
                assert!((e - want).abs() < 1e-5, "l={l} d={d:?}: {e} vs {want}");
            }
        }
    }

    #[test]
    fn trunc_exp_clamps() {
        assert_eq!(trunc_exp(0.0), (1.0, 1.0));
        let (v, d) = trunc_exp(100.0);
        assert!(v.is_finite() && d.is_finite());
        let (_, d) = trunc_exp(-100.0);
        assert!(d > 0.0);
    }
}
