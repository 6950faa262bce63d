//! Small PNG charts for the reports (sparsification curves, error vs uncertainty), drawn with the `image`
//! crate and a built-in 5×7 bitmap font, so they render the same natively and in wasm with no font files.

use image::{Rgb, RgbImage};

const W: u32 = 720;
const H: u32 = 480;
const LEFT: i32 = 70;
const RIGHT: i32 = 20;
const TOP: i32 = 40;
const BOTTOM: i32 = 50;

/// Line colours, in series order.
pub const PALETTE: [[u8; 3]; 6] = [
    [20, 20, 20],
    [214, 39, 40],
    [31, 119, 180],
    [44, 160, 44],
    [148, 103, 189],
    [150, 150, 150],
];

/// A named series of (x, y) points.
pub struct Series<'a> {
    pub name: &'a str,
    pub x: &'a [f64],
    pub y: &'a [f64],
    pub colour: [u8; 3],
}

/// 5×7 glyphs, one byte per row (low 5 bits, MSB left). Lower case is drawn as upper case.
fn glyph(c: char) -> [u8; 7] {
    match c.to_ascii_uppercase() {
        '0' => [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E],
        '1' => [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E],
        '2' => [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F],
        '3' => [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E],
        '4' => [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02],
        '5' => [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E],
        '6' => [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E],
        '7' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08],
        '8' => [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E],
        '9' => [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C],
        'A' => [0x0E, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'B' => [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E],
        'C' => [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E],
        'D' => [0x1C, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1C],
        'E' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F],
        'F' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10],
        'G' => [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F],
        'H' => [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'I' => [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E],
        'J' => [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C],
        'K' => [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11],
        'L' => [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F],
        'M' => [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11],
        'N' => [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11],
        'O' => [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'P' => [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10],
        'Q' => [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D],
        'R' => [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11],
        'S' => [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E],
        'T' => [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04],
        'U' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'V' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04],
        'W' => [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A],
        'X' => [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11],
        'Y' => [0x11, 0x11, 0x11, 0x0A, 0x04, 0x04, 0x04],
        'Z' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F],
        '.' => [0, 0, 0, 0, 0, 0x0C, 0x0C],
        ',' => [0, 0, 0, 0, 0x0C, 0x04, 0x08],
        '-' => [0, 0, 0, 0x1F, 0, 0, 0],
        '+' => [0, 0x04, 0x04, 0x1F, 0x04, 0x04, 0],
        '=' => [0, 0, 0x1F, 0, 0x1F, 0, 0],
        ':' => [0, 0x0C, 0x0C, 0, 0x0C, 0x0C, 0],
        '/' => [0, 0x01, 0x02, 0x04, 0x08, 0x10, 0],
        '(' => [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02],
        ')' => [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08],
        '%' => [0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03],
        '_' => [0, 0, 0, 0, 0, 0, 0x1F],
        _ => [0; 7],
    }
}

fn put(img: &mut RgbImage, x: i32, y: i32, c: [u8; 3]) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, Rgb(c));
    }
}

/// Text at (x, y) (top-left), `scale` pixels per font pixel.
pub fn text(img: &mut RgbImage, x: i32, y: i32, s: &str, scale: i32, c: [u8; 3]) {
    for (k, ch) in s.chars().enumerate() {
        let g = glyph(ch);
        let ox = x + k as i32 * 6 * scale;
        for (row, bits) in g.iter().enumerate() {
            for col in 0..5 {
                if bits & (0x10 >> col) != 0 {
                    for dy in 0..scale {
                        for dx in 0..scale {
                            put(img, ox + col * scale + dx, y + row as i32 * scale + dy, c);
                        }
                    }
                }
            }
        }
    }
}

fn text_width(s: &str, scale: i32) -> i32 {
    s.chars().count() as i32 * 6 * scale
}

/// A line from (x0, y0) to (x1, y1), `thick` pixels wide (Bresenham with a square pen).
pub fn line(img: &mut RgbImage, p0: (i32, i32), p1: (i32, i32), c: [u8; 3], thick: i32) {
    let (mut x0, mut y0) = p0;
    let (x1, y1) = p1;
    let dx = (x1 - x0).abs();
    let dy = -(y1 - y0).abs();
    let sx = if x0 < x1 { 1 } else { -1 };
    let sy = if y0 < y1 { 1 } else { -1 };
    let mut err = dx + dy;
    let h = thick / 2;
    loop {
        for a in -h..thick - h {
            for b in -h..thick - h {
                put(img, x0 + a, y0 + b, c);
            }
        }
        if x0 == x1 && y0 == y1 {
            break;
        }
        let e2 = 2 * err;
        if e2 >= dy {
            err += dy;
            x0 += sx;
        }
        if e2 <= dx {
            err += dx;
            y0 += sy;
        }
    }
}

/// Tick label with few digits.
fn tick_label(v: f64) -> String {
    if v == 0.0 {
        return "0".into();
    }
    let a = v.abs();
    if !(1e-3..1e4).contains(&a) {
        format!("{v:.0e}")
    } else if a >= 100.0 {
        format!("{v:.0}")
    } else if a >= 1.0 {
        format!("{v:.1}")
    } else {
        format!("{v:.2}")
    }
}

/// The axes' frame: maps data to pixels.
struct Frame {
    x: (f64, f64),
    y: (f64, f64),
}

impl Frame {
    fn px(&self, x: f64, y: f64) -> (i32, i32) {
        let fx = (x - self.x.0) / (self.x.1 - self.x.0).max(1e-300);
        let fy = (y - self.y.0) / (self.y.1 - self.y.0).max(1e-300);
        let w = W as i32 - LEFT - RIGHT;
        let h = H as i32 - TOP - BOTTOM;
        (
            LEFT + (fx * w as f64).round() as i32,
            TOP + h - (fy * h as f64).round() as i32,
        )
    }
}

fn axes(img: &mut RgbImage, f: &Frame, title: &str, xlabel: &str, ylabel: &str) {
    let grey = [200, 200, 200];
    let black = [0, 0, 0];
    for k in 0..=5 {
        let xv = f.x.0 + (f.x.1 - f.x.0) * k as f64 / 5.0;
        let yv = f.y.0 + (f.y.1 - f.y.0) * k as f64 / 5.0;
        let (px, _) = f.px(xv, f.y.0);
        let (_, py) = f.px(f.x.0, yv);
        line(img, (px, TOP), (px, H as i32 - BOTTOM), grey, 1);
        line(img, (LEFT, py), (W as i32 - RIGHT, py), grey, 1);
        let xl = tick_label(xv);
        text(
            img,
            px - text_width(&xl, 1) / 2,
            H as i32 - BOTTOM + 6,
            &xl,
            1,
            black,
        );
        let yl = tick_label(yv);
        text(img, LEFT - 6 - text_width(&yl, 1), py - 3, &yl, 1, black);
    }
    line(img, (LEFT, TOP), (LEFT, H as i32 - BOTTOM), black, 1);
    line(
        img,
        (LEFT, H as i32 - BOTTOM),
        (W as i32 - RIGHT, H as i32 - BOTTOM),
        black,
        1,
    );
    text(
        img,
        (W as i32 - text_width(title, 2)) / 2,
        10,
        title,
        2,
        black,
    );
    text(
        img,
        (W as i32 - text_width(xlabel, 1)) / 2,
        H as i32 - 18,
        xlabel,
        1,
        black,
    );
    // The y label runs along the top of the axis (no rotated text).
    text(img, 4, TOP - 14, ylabel, 1, black);
}

fn range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values.filter(|v| v.is_finite()) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    if hi - lo < 1e-12 {
        return (lo - 0.5, hi + 0.5);
    }
    (lo, hi)
}

/// A line chart of `series` with a legend (top right).
pub fn line_chart(title: &str, xlabel: &str, ylabel: &str, series: &[Series]) -> RgbImage {
    let mut img = RgbImage::from_pixel(W, H, Rgb([255, 255, 255]));
    let f = Frame {
        x: range(series.iter().flat_map(|s| s.x.iter().cloned())),
        y: {
            let (lo, hi) = range(series.iter().flat_map(|s| s.y.iter().cloned()));
            (lo.min(0.0), hi)
        },
    };
    axes(&mut img, &f, title, xlabel, ylabel);
    for s in series {
        let pts: Vec<(i32, i32)> =
            s.x.iter()
                .zip(s.y)
                .filter(|(x, y)| x.is_finite() && y.is_finite())
                .map(|(&x, &y)| f.px(x, y))
                .collect();
        for w in pts.windows(2) {
            line(&mut img, w[0], w[1], s.colour, 2);
        }
    }
    for (k, s) in series.iter().enumerate() {
        let y = TOP + 8 + 14 * k as i32;
        let x = W as i32 - RIGHT - 170;
        line(&mut img, (x, y + 3), (x + 20, y + 3), s.colour, 3);
        text(&mut img, x + 26, y, s.name, 1, [0, 0, 0]);
    }
    img
}

/// A 2-D histogram (log-density shading) of (x, y) pairs, with the mean y per x bin drawn over it.
pub fn density_chart(title: &str, xlabel: &str, ylabel: &str, x: &[f64], y: &[f64]) -> RgbImage {
    let mut img = RgbImage::from_pixel(W, H, Rgb([255, 255, 255]));
    let f = Frame {
        x: range(x.iter().cloned()),
        y: range(y.iter().cloned()),
    };
    axes(&mut img, &f, title, xlabel, ylabel);
    const B: usize = 60;
    let mut hist = vec![0u32; B * B];
    let mut sum = [0.0f64; B];
    let mut cnt = [0u32; B];
    for (&a, &b) in x.iter().zip(y) {
        if !(a.is_finite() && b.is_finite()) {
            continue;
        }
        let bx = (((a - f.x.0) / (f.x.1 - f.x.0)) * B as f64).clamp(0.0, B as f64 - 1.0) as usize;
        let by = (((b - f.y.0) / (f.y.1 - f.y.0)) * B as f64).clamp(0.0, B as f64 - 1.0) as usize;
        hist[by * B + bx] += 1;
        sum[bx] += b;
        cnt[bx] += 1;
    }
    let maxc = hist.iter().cloned().max().unwrap_or(1).max(1) as f64;
    for by in 0..B {
        for bx in 0..B {
            let c = hist[by * B + bx];
            if c == 0 {
                continue;
            }
            let s = ((c as f64).ln_1p() / maxc.ln_1p()).clamp(0.0, 1.0);
            let col = [
                (230.0 - 200.0 * s) as u8,
                (235.0 - 150.0 * s) as u8,
                (255.0 - 60.0 * s) as u8,
            ];
            let x0 = f.x.0 + (f.x.1 - f.x.0) * bx as f64 / B as f64;
            let x1 = f.x.0 + (f.x.1 - f.x.0) * (bx + 1) as f64 / B as f64;
            let y0 = f.y.0 + (f.y.1 - f.y.0) * by as f64 / B as f64;
            let y1 = f.y.0 + (f.y.1 - f.y.0) * (by + 1) as f64 / B as f64;
            let (px0, py1) = f.px(x0, y0);
            let (px1, py0) = f.px(x1, y1);
            for py in py0..py1.max(py0 + 1) {
                for px in px0..px1.max(px0 + 1) {
                    put(&mut img, px, py, col);
                }
            }
        }
    }
    let means: Vec<(i32, i32)> = (0..B)
        .filter(|&b| cnt[b] > 0)
        .map(|b| {
            let xc = f.x.0 + (f.x.1 - f.x.0) * (b as f64 + 0.5) / B as f64;
            f.px(xc, sum[b] / cnt[b] as f64)
        })
        .collect();
    for w in means.windows(2) {
        line(&mut img, w[0], w[1], PALETTE[1], 2);
    }
    text(
        &mut img,
        W as i32 - RIGHT - 110,
        TOP + 8,
        "mean per bin",
        1,
        PALETTE[1],
    );
    img
}

/// PNG bytes of an image.
pub fn png_bytes(img: &RgbImage) -> Vec<u8> {
    let mut out = Vec::new();
    // Encoding an in-memory RGB8 image to a Vec cannot fail.
    let _ = img.write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn charts_draw_their_series_and_labels() {
        let x: Vec<f64> = (0..100).map(|i| i as f64 / 100.0).collect();
        let y: Vec<f64> = x.iter().map(|v| 1.0 - v).collect();
        let img = line_chart(
            "Sparsification",
            "fraction removed",
            "mean error",
            &[Series {
                name: "oracle",
                x: &x,
                y: &y,
                colour: PALETTE[1],
            }],
        );
        assert_eq!(img.dimensions(), (W, H));
        let red = img.pixels().filter(|p| p.0 == PALETTE[1]).count();
        assert!(red > 500, "the series is drawn ({red} pixels)");
        let dark = img.pixels().filter(|p| p.0 == [0, 0, 0]).count();
        assert!(dark > 1000, "axes and text are drawn ({dark} pixels)");
        let png = png_bytes(&img);
        assert_eq!(&png[1..4], b"PNG");
        let d = density_chart("e", "u", "err", &x, &y);
        assert!(d.pixels().filter(|p| p.0 == PALETTE[1]).count() > 100);
        // Every character we print has a glyph.
        for c in "0123456789abcdefghijklmnopqrstuvwxyz.,-+=:/()%_".chars() {
            assert!(glyph(c) != [0; 7], "{c}");
        }
    }
}
