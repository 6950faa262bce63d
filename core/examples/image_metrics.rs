//! Prints PSNR and SSIM of two RGB images as JSON (`{"psnr": …, "ssim": …}`); used by
//! `scripts/crosscheck_eval.py` to compare our SSIM with scikit-image's.
//!
//! `cargo run -p silvr-core --example image_metrics -- A.png B.png`

use silvr_core::eval::{psnr_rgb8, ssim_rgb8};
use std::process::ExitCode;

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [a, b] = args.as_slice() else {
        eprintln!("usage: image_metrics A.png B.png");
        return ExitCode::FAILURE;
    };
    let load = |p: &str| {
        image::open(p)
            .map(|i| i.to_rgb8())
            .map_err(|e| format!("{p}: {e}"))
    };
    let (a, b) = match (load(a), load(b)) {
        (Ok(a), Ok(b)) => (a, b),
        (Err(e), _) | (_, Err(e)) => {
            eprintln!("image_metrics: {e}");
            return ExitCode::FAILURE;
        }
    };
    match (psnr_rgb8(&a, &b, None), ssim_rgb8(&a, &b, None)) {
        (Ok(p), Ok(s)) => {
            // JSON has no infinity; identical images report psnr null.
            println!(
                "{}",
                serde_json::json!({ "psnr": p.is_finite().then_some(p), "ssim": s })
            );
            ExitCode::SUCCESS
        }
        (Err(e), _) | (_, Err(e)) => {
            eprintln!("image_metrics: {e}");
            ExitCode::FAILURE
        }
    }
}
