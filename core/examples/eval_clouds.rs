//! Scores one PLY cloud against another and prints the report (and optionally per-point distances) as
//! JSON; `scripts/crosscheck_eval.py` compares its output with SciPy's cKDTree.
//!
//! ```text
//! cargo run -p silvr-core --example eval_clouds -- REC.ply GT.ply [--raw] [--distances]
//!     [--thresholds 0.03,0.05,0.1,0.2] [--voxel 0.01] [--observed observed.bin] [--error-cloud OUT.ply]
//! ```
//! `--raw` disables cropping, downsampling and the unknown-space filter (exact comparison).

use silvr_core::eval::{
    error_colored_cloud, evaluate_geometry, GeometryOptions, ObservedSpace, OccupancyGrid,
};
use silvr_core::pointcloud::{read_ply, write_ply};
use std::path::PathBuf;
use std::process::ExitCode;

fn main() -> ExitCode {
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("eval_clouds: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run() -> Result<(), String> {
    let mut args = std::env::args().skip(1);
    let mut paths = Vec::new();
    let mut opts = GeometryOptions::default();
    let mut distances = false;
    let mut observed = None;
    let mut error_cloud = None;
    while let Some(a) = args.next() {
        let mut value = |name: &str| args.next().ok_or(format!("{name} needs a value"));
        match a.as_str() {
            "--raw" => {
                opts = GeometryOptions {
                    thresholds_m: opts.thresholds_m,
                    ..GeometryOptions::raw()
                }
            }
            "--distances" => distances = true,
            "--thresholds" => {
                opts.thresholds_m = value("--thresholds")?
                    .split(',')
                    .map(|t| {
                        t.trim()
                            .parse::<f64>()
                            .map_err(|e| format!("bad threshold '{t}': {e}"))
                    })
                    .collect::<Result<_, _>>()?
            }
            "--voxel" => {
                let v: f64 = value("--voxel")?
                    .parse()
                    .map_err(|e| format!("bad voxel size: {e}"))?;
                opts.voxel_size_m = (v > 0.0).then_some(v);
            }
            "--observed" => observed = Some(PathBuf::from(value("--observed")?)),
            "--error-cloud" => error_cloud = Some(PathBuf::from(value("--error-cloud")?)),
            s if s.starts_with("--") => return Err(format!("unknown option {s}")),
            _ => paths.push(PathBuf::from(a)),
        }
    }
    let [rec, gt] = paths.as_slice() else {
        return Err("usage: eval_clouds REC.ply GT.ply [options] (see the source)".into());
    };
    let rec = read_ply(rec).map_err(|e| e.to_string())?;
    let gt = read_ply(gt).map_err(|e| e.to_string())?;
    let grid = observed
        .map(|p| OccupancyGrid::load(&p))
        .transpose()
        .map_err(|e| e.to_string())?;
    let eval = evaluate_geometry(
        &rec,
        &gt,
        ObservedSpace {
            gt: grid.as_ref(),
            sensor: None,
        },
        &opts,
    )
    .map_err(|e| e.to_string())?;
    if let Some(path) = error_cloud {
        let colored = error_colored_cloud(&eval.reconstruction, &eval.rec_to_gt, 1.0);
        write_ply(&path, &colored).map_err(|e| e.to_string())?;
    }
    let mut out = serde_json::json!({ "report": eval.report });
    if distances {
        out["rec_to_gt"] = serde_json::json!(eval.rec_to_gt);
        out["gt_to_rec"] = serde_json::json!(eval.gt_to_rec);
    }
    println!("{out}");
    Ok(())
}
