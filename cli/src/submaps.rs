//! `silvr submaps`: a dataset cut into submaps (silvr_core::submap), one folder each, written under a
//! temporary name and renamed into place as a whole.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

/// `silvr submaps`: the plan (silvr_core::submap), then one folder per submap, written under a
/// temporary name and renamed into place as a whole.
pub fn run(
    dataset: &Path,
    out: &Path,
    method: &str,
    max_images: Option<usize>,
    count: Option<usize>,
    overlap: f64,
    data_root: Option<&Path>,
) -> Result<silvr_core::submap::Plan> {
    use silvr_core::submap::{self, Limit, Method, SubmapOptions};
    let method = match method {
        "distance" => Method::Distance,
        "covis" => Method::Covis,
        other => anyhow::bail!("--method {other}: expected distance or covis"),
    };
    let limit = match (count, max_images) {
        (Some(0), _) | (_, Some(0)) => anyhow::bail!("--count and --max-images must be at least 1"),
        (Some(c), _) => Limit::Count(c),
        (None, m) => Limit::MaxImages(m.unwrap_or(300)),
    };
    if !(overlap.is_finite() && overlap >= 0.0) {
        anyhow::bail!("--overlap {overlap}: expected a distance in metres ≥ 0");
    }
    let json = crate::transforms_file(dataset);
    let root_dir = json.parent().unwrap_or(Path::new(".")).to_path_buf();
    let text =
        std::fs::read_to_string(&json).with_context(|| format!("reading {}", json.display()))?;
    let (frames, _, _) = silvr_core::dataset::parse_frames(&text, &json)?;
    let value: serde_json::Value = serde_json::from_str(&text)?;
    let opts = SubmapOptions {
        method,
        limit,
        overlap_m: overlap,
        neighbours: 10,
    };
    // Lidar co-visibility: what --method covis cuts by, and what scores either cut.
    let has_lidar = frames.iter().any(|f| f.depth_file_path.is_some());
    let voxels = if has_lidar {
        let src = match data_root {
            Some(r) => silvr_core::source::Dir::within(&root_dir, r)?,
            None => silvr_core::source::Dir::new(&root_dir),
        };
        Some(submap::lidar_voxels(&src, &frames, &json)?)
    } else {
        None
    };
    // SfM tracks, when the dataset is a `silvr poses` output (its COLMAP model beside transforms.json).
    let model_dir = root_dir.join("colmap");
    let tracks = if model_dir.join("images.txt").is_file() {
        let model = silvr_core::ingest::colmap::read_model(&model_dir)
            .with_context(|| format!("reading the tracks of {}", model_dir.display()))?;
        Some(submap::track_sets(&model, frames.len()).with_context(|| {
            format!(
                "{} does not hold one image per frame of {} in order (not written by silvr poses?)",
                model_dir.display(),
                json.display()
            )
        })?)
    } else {
        None
    };
    let plan = submap::plan(&frames, &json, voxels.as_deref(), tracks.as_deref(), &opts)?;
    if out.exists() {
        anyhow::bail!("{} exists; choose a new folder", out.display());
    }
    let tmp = staging(out)?;
    // The way from a submap's folder (out/submap_k/) back to the dataset.
    let prefix = prefix_to(&root_dir, &out.join("submap_00"))?;
    for sub in &plan.submaps {
        let dir = tmp.join(&sub.name);
        std::fs::create_dir_all(&dir)?;
        let tf = submap::submap_transforms(&value, sub, &prefix);
        std::fs::write(dir.join("transforms.json"), serde_json::to_vec_pretty(&tf)?)?;
    }
    std::fs::write(tmp.join("manifest.json"), serde_json::to_vec_pretty(&plan)?)?;
    std::fs::write(
        tmp.join("submaps.png"),
        silvr_core::eval::plot::png_bytes(&submap::plot(&plan)),
    )?;
    std::fs::rename(&tmp, out).with_context(|| format!("moving {} into place", out.display()))?;
    for s in &plan.submaps {
        eprintln!(
            "{}: {} keyframes + {} shared, {} images",
            s.name,
            s.keyframes.len(),
            s.overlap.len(),
            s.frames.len()
        );
    }
    let covis = plan.covis_cut.map_or(String::new(), |c| {
        format!(
            "; {:.1} % of the co-visible structure spans a boundary",
            100.0 * c.shared / c.total.max(1.0)
        )
    });
    let tracks = plan.track_cut.map_or(String::new(), |c| {
        format!(
            "; {:.1} % of the shared SfM tracks",
            100.0 * c.shared / c.total.max(1.0)
        )
    });
    let covis = format!("{covis}{tracks}");
    // A submap names the dataset's images from beside it: training reads them under a folder holding both.
    let root = crate::data_root(dataset, out)?;
    eprintln!(
        "{} submaps of {} keyframes by {:?} (cut weight {:.1}{covis}) in {}; train one with: silvr train {} --data-root {}",
        plan.submaps.len(),
        plan.nodes.len(),
        plan.method,
        plan.cut_weight,
        out.display(),
        out.join("submap_00").display(),
        root.display()
    );
    Ok(plan)
}

/// `target` relative to the folder `base` (both absolute): `../../dataset` and the like.
pub fn relative_path(target: &Path, base: &Path) -> PathBuf {
    let t: Vec<_> = target.components().collect();
    let b: Vec<_> = base.components().collect();
    let common = t.iter().zip(&b).take_while(|(x, y)| x == y).count();
    let mut rel = PathBuf::new();
    for _ in common..b.len() {
        rel.push("..");
    }
    for c in &t[common..] {
        rel.push(c.as_os_str());
    }
    rel
}

/// `OUT`'s staging folder (`.OUT.partial` beside it, emptied): written in full, then renamed to `OUT`.
pub(crate) fn staging(out: &Path) -> Result<PathBuf> {
    let parent = out
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    let tmp = parent.join(format!(
        ".{}.partial",
        out.file_name()
            .map(|n| n.to_string_lossy())
            .unwrap_or_default()
    ));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).with_context(|| format!("creating {}", tmp.display()))?;
    Ok(tmp)
}

/// The path from folder `out` back to `root_dir`, as a prefix for relative paths (`""` or `"a/b/"`).
pub(crate) fn prefix_to(root_dir: &Path, out: &Path) -> Result<String> {
    let abs = |p: &Path| -> Result<PathBuf> {
        std::path::absolute(p).with_context(|| format!("resolving {}", p.display()))
    };
    let rel = relative_path(&abs(root_dir)?, &abs(out)?);
    let s = rel.to_string_lossy().replace('\\', "/");
    Ok(if s.is_empty() { s } else { format!("{s}/") })
}
