//! Image metrics for novel-view synthesis: PSNR and SSIM on RGB images with values in [0, 1].
//!
//! SSIM follows scikit-image's `structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
//! use_sample_covariance=False, data_range=1, channel_axis=-1)`: an 11×11 Gaussian window (σ = 1.5,
//! truncated at 3.5σ, weights normalised), local statistics by separable filtering with SciPy's
//! `reflect` border (`d c b a | a b c d`), K1 = 0.01, K2 = 0.03, population covariances, the SSIM map
//! averaged over the image minus a 5-pixel border, then over the three channels. Computed in f64.
//! `scripts/crosscheck_eval.py` checks this against a SciPy port of that code.

use image::{Rgb32FImage, RgbImage};
use thiserror::Error;

#[derive(Clone, Debug, PartialEq, Error)]
pub enum ImageMetricError {
    #[error("image sizes differ: {a:?} vs {b:?}")]
    SizeMismatch { a: (u32, u32), b: (u32, u32) },
    #[error("mask has {got} entries, image has {want} pixels")]
    MaskSize { got: usize, want: usize },
    #[error("mask selects no pixel that the metric can use")]
    EmptyMask,
    #[error("SSIM needs images of at least 11×11 pixels, got {0}×{1}")]
    TooSmall(u32, u32),
}

/// SSIM constants and window (fixed by the skimage settings we match).
const K1: f64 = 0.01;
const K2: f64 = 0.03;
const SIGMA: f64 = 1.5;
const RADIUS: usize = 5; // int(3.5 · 1.5 + 0.5)
const WIN: usize = 2 * RADIUS + 1;

/// An RGB image as three f64 planes (row-major), the form both metrics work on.
struct Planes {
    w: usize,
    h: usize,
    c: [Vec<f64>; 3],
}

impl Planes {
    fn from_f32(img: &Rgb32FImage) -> Self {
        let c = [0, 1, 2].map(|k| img.pixels().map(|p| p.0[k] as f64).collect());
        Self {
            w: img.width() as usize,
            h: img.height() as usize,
            c,
        }
    }

    /// v / 255 in f64, so 8-bit metrics carry no f32 rounding.
    fn from_rgb8(img: &RgbImage) -> Self {
        let c = [0, 1, 2].map(|k| img.pixels().map(|p| p.0[k] as f64 / 255.0).collect());
        Self {
            w: img.width() as usize,
            h: img.height() as usize,
            c,
        }
    }

    fn dims(&self) -> (u32, u32) {
        (self.w as u32, self.h as u32)
    }
}

fn check(a: &Planes, b: &Planes, mask: Option<&[bool]>) -> Result<(), ImageMetricError> {
    if a.dims() != b.dims() {
        return Err(ImageMetricError::SizeMismatch {
            a: a.dims(),
            b: b.dims(),
        });
    }
    if let Some(m) = mask {
        if m.len() != a.w * a.h {
            return Err(ImageMetricError::MaskSize {
                got: m.len(),
                want: a.w * a.h,
            });
        }
    }
    Ok(())
}

/// Converts 8-bit RGB to [0, 1] floats (v / 255).
pub fn rgb8_to_f32(img: &RgbImage) -> Rgb32FImage {
    Rgb32FImage::from_fn(img.width(), img.height(), |x, y| {
        let p = img.get_pixel(x, y).0;
        image::Rgb(p.map(|v| v as f32 / 255.0))
    })
}

/// PSNR in dB with data range 1: `10·log10(1 / MSE)`, MSE over all channels of the (masked) pixels.
/// Identical images give +∞. `mask` is row-major, one entry per pixel.
pub fn psnr(
    a: &Rgb32FImage,
    b: &Rgb32FImage,
    mask: Option<&[bool]>,
) -> Result<f64, ImageMetricError> {
    psnr_planes(&Planes::from_f32(a), &Planes::from_f32(b), mask)
}

/// [`psnr`] on 8-bit images (values / 255, so equal to PSNR with data range 255).
pub fn psnr_rgb8(
    a: &RgbImage,
    b: &RgbImage,
    mask: Option<&[bool]>,
) -> Result<f64, ImageMetricError> {
    psnr_planes(&Planes::from_rgb8(a), &Planes::from_rgb8(b), mask)
}

fn psnr_planes(a: &Planes, b: &Planes, mask: Option<&[bool]>) -> Result<f64, ImageMetricError> {
    check(a, b, mask)?;
    let mut sum = 0.0f64;
    let mut n = 0usize;
    for i in 0..a.w * a.h {
        if mask.is_some_and(|m| !m[i]) {
            continue;
        }
        for c in 0..3 {
            let d = a.c[c][i] - b.c[c][i];
            sum += d * d;
        }
        n += 3;
    }
    if n == 0 {
        return Err(ImageMetricError::EmptyMask);
    }
    let mse = sum / n as f64;
    Ok(if mse == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    })
}

/// Mean SSIM (module docs). With a mask, the SSIM map is averaged over the masked pixels inside the
/// 5-pixel border only (the local statistics still use the whole image).
pub fn ssim(
    a: &Rgb32FImage,
    b: &Rgb32FImage,
    mask: Option<&[bool]>,
) -> Result<f64, ImageMetricError> {
    ssim_planes(&Planes::from_f32(a), &Planes::from_f32(b), mask)
}

/// [`ssim`] on 8-bit images (values / 255; equal to skimage with data range 255 on the raw values).
pub fn ssim_rgb8(
    a: &RgbImage,
    b: &RgbImage,
    mask: Option<&[bool]>,
) -> Result<f64, ImageMetricError> {
    ssim_planes(&Planes::from_rgb8(a), &Planes::from_rgb8(b), mask)
}

fn ssim_planes(a: &Planes, b: &Planes, mask: Option<&[bool]>) -> Result<f64, ImageMetricError> {
    check(a, b, mask)?;
    let (w, h) = (a.w, a.h);
    if w < WIN || h < WIN {
        return Err(ImageMetricError::TooSmall(w as u32, h as u32));
    }
    let used = |x: usize, y: usize| {
        x >= RADIUS
            && x < w - RADIUS
            && y >= RADIUS
            && y < h - RADIUS
            && mask.is_none_or(|m| m[y * w + x])
    };
    let n_used = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .filter(|&(x, y)| used(x, y))
        .count();
    if n_used == 0 {
        return Err(ImageMetricError::EmptyMask);
    }
    let kernel = gaussian_kernel();
    let (c1, c2) = ((K1 * 1.0).powi(2), (K2 * 1.0).powi(2));
    let mut total = 0.0;
    for c in 0..3 {
        let (x, y) = (&a.c[c], &b.c[c]);
        let xx: Vec<f64> = x.iter().map(|v| v * v).collect();
        let yy: Vec<f64> = y.iter().map(|v| v * v).collect();
        let xy: Vec<f64> = x.iter().zip(y).map(|(p, q)| p * q).collect();
        let [ux, uy, uxx, uyy, uxy] = [x, y, &xx, &yy, &xy].map(|img| filter(img, w, h, &kernel));
        let mut sum = 0.0;
        for row in 0..h {
            for col in 0..w {
                if !used(col, row) {
                    continue;
                }
                let i = row * w + col;
                let (mx, my) = (ux[i], uy[i]);
                let vx = uxx[i] - mx * mx;
                let vy = uyy[i] - my * my;
                let vxy = uxy[i] - mx * my;
                sum += ((2.0 * mx * my + c1) * (2.0 * vxy + c2))
                    / ((mx * mx + my * my + c1) * (vx + vy + c2));
            }
        }
        total += sum / n_used as f64;
    }
    Ok(total / 3.0)
}

/// SciPy's `gaussian_filter1d` weights: exp(−x²/2σ²) for |x| ≤ 5, normalised to sum 1.
fn gaussian_kernel() -> [f64; WIN] {
    let mut k = [0.0; WIN];
    for (i, v) in k.iter_mut().enumerate() {
        let x = i as f64 - RADIUS as f64;
        *v = (-0.5 * x * x / (SIGMA * SIGMA)).exp();
    }
    let s: f64 = k.iter().sum();
    k.map(|v| v / s)
}

/// SciPy `reflect` index for `i` in `[-RADIUS, n + RADIUS)`, `n > RADIUS`.
#[inline]
fn reflect(i: isize, n: usize) -> usize {
    let n = n as isize;
    let j = if i < 0 {
        -i - 1
    } else if i >= n {
        2 * n - i - 1
    } else {
        i
    };
    j as usize
}

/// Separable 2-D filtering (rows, then columns) with the reflect border.
fn filter(img: &[f64], w: usize, h: usize, k: &[f64; WIN]) -> Vec<f64> {
    let mut tmp = vec![0.0; w * h];
    for y in 0..h {
        let row = &img[y * w..(y + 1) * w];
        for x in 0..w {
            let mut s = 0.0;
            for (t, kv) in k.iter().enumerate() {
                s += kv * row[reflect(x as isize + t as isize - RADIUS as isize, w)];
            }
            tmp[y * w + x] = s;
        }
    }
    let mut out = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut s = 0.0;
            for (t, kv) in k.iter().enumerate() {
                s += kv * tmp[reflect(y as isize + t as isize - RADIUS as isize, h) * w + x];
            }
            out[y * w + x] = s;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_xoshiro::Xoshiro256PlusPlus;

    fn random_image(w: u32, h: u32, seed: u64) -> Rgb32FImage {
        let mut r = Xoshiro256PlusPlus::seed_from_u64(seed);
        // Smooth-ish content plus texture, like a photo.
        Rgb32FImage::from_fn(w, h, |x, y| {
            let base = 0.5 + 0.3 * ((x as f32 * 0.2).sin() * (y as f32 * 0.15).cos());
            image::Rgb(
                [0, 1, 2]
                    .map(|c| (base + 0.1 * c as f32 + r.random_range(-0.1..0.1)).clamp(0.0, 1.0)),
            )
        })
    }

    fn add_noise(img: &Rgb32FImage, amp: f32, seed: u64) -> Rgb32FImage {
        let mut r = Xoshiro256PlusPlus::seed_from_u64(seed);
        let mut out = img.clone();
        for p in out.pixels_mut() {
            for v in &mut p.0 {
                *v = (*v + r.random_range(-amp..amp)).clamp(0.0, 1.0);
            }
        }
        out
    }

    #[test]
    fn psnr_identical_and_constant_offset() {
        let a = random_image(32, 24, 1);
        assert_eq!(psnr(&a, &a, None).unwrap(), f64::INFINITY);
        // Offset by exactly 1/16 (representable, no clamping for a constant 0.5 image): MSE = 1/256.
        let flat = Rgb32FImage::from_pixel(16, 16, image::Rgb([0.5, 0.5, 0.5]));
        let off = Rgb32FImage::from_pixel(16, 16, image::Rgb([0.5625, 0.4375, 0.5625]));
        let want = 10.0 * 256f64.log10();
        assert!((psnr(&flat, &off, None).unwrap() - want).abs() < 1e-12);
        // 8-bit: a difference of 10 levels everywhere.
        let a8 = RgbImage::from_pixel(8, 8, image::Rgb([100, 100, 100]));
        let b8 = RgbImage::from_pixel(8, 8, image::Rgb([110, 110, 110]));
        let want8 = 20.0 * (255.0f64 / 10.0).log10();
        assert!((psnr_rgb8(&a8, &b8, None).unwrap() - want8).abs() < 1e-10);
    }

    #[test]
    fn psnr_mask_selects_pixels() {
        let a = Rgb32FImage::from_pixel(4, 1, image::Rgb([0.0, 0.0, 0.0]));
        let mut b = a.clone();
        b.put_pixel(3, 0, image::Rgb([1.0, 1.0, 1.0]));
        assert_eq!(
            psnr(&a, &b, Some(&[true, true, true, false])).unwrap(),
            f64::INFINITY
        );
        assert!((psnr(&a, &b, None).unwrap() - 10.0 * 4f64.log10()).abs() < 1e-12);
        assert_eq!(
            psnr(&a, &b, Some(&[false; 4])),
            Err(ImageMetricError::EmptyMask)
        );
        assert!(matches!(
            psnr(&a, &b, Some(&[true; 3])),
            Err(ImageMetricError::MaskSize { .. })
        ));
    }

    #[test]
    fn ssim_identical_is_one_and_noise_lowers_it() {
        let a = random_image(40, 30, 2);
        assert!((ssim(&a, &a, None).unwrap() - 1.0).abs() < 1e-12);
        let mut last = 1.0;
        for amp in [0.02, 0.1, 0.3] {
            let s = ssim(&a, &add_noise(&a, amp, 7), None).unwrap();
            assert!(s < last, "amp {amp}: {s} not below {last}");
            last = s;
        }
        assert!(last < 0.5, "{last}");
        // Symmetric in its arguments.
        let b = add_noise(&a, 0.1, 8);
        assert!((ssim(&a, &b, None).unwrap() - ssim(&b, &a, None).unwrap()).abs() < 1e-12);
    }

    #[test]
    fn ssim_mask_and_errors() {
        let a = random_image(20, 20, 3);
        let mut b = a.clone();
        // Corrupt the left half only; a mask over the right interior sees a perfect match.
        for y in 0..20 {
            for x in 0..6 {
                b.put_pixel(x, y, image::Rgb([0.0, 1.0, 0.0]));
            }
        }
        let mask: Vec<bool> = (0..400).map(|i| i % 20 >= 12).collect();
        assert!((ssim(&a, &b, Some(&mask)).unwrap() - 1.0).abs() < 1e-12);
        assert!(ssim(&a, &b, None).unwrap() < 0.9);
        let small = random_image(10, 30, 4);
        assert_eq!(
            ssim(&small, &small, None),
            Err(ImageMetricError::TooSmall(10, 30))
        );
        let other = random_image(20, 21, 4);
        assert!(matches!(
            ssim(&a, &other, None),
            Err(ImageMetricError::SizeMismatch { .. })
        ));
        let border_only: Vec<bool> = (0..400).map(|i| i % 20 < 5).collect();
        assert_eq!(
            ssim(&a, &b, Some(&border_only)),
            Err(ImageMetricError::EmptyMask)
        );
    }

    #[test]
    fn kernel_matches_scipy() {
        let k = gaussian_kernel();
        assert!((k.iter().sum::<f64>() - 1.0).abs() < 1e-15);
        // exp(-x²/4.5) / Σ for x = 0 and x = ±5 (what scipy.ndimage's _gaussian_kernel1d(1.5, 0, 5) holds).
        assert!((k[5] - 0.266_011_724_861_794_36).abs() < 1e-15, "{}", k[5]);
        assert!(
            (k[0] - 0.001_028_380_084_479_11).abs() < 1e-17 && k[0] == k[10],
            "{}",
            k[0]
        );
    }
}
