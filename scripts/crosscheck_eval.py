#!/usr/bin/env python3
"""Cross-checks silvr-core's evaluation code against SciPy.

Writes seeded random point clouds as PLY (binary little-endian doubles with extra properties and a face
element, ASCII floats, binary big-endian floats) into a temporary folder, runs
`cargo run -p silvr-core --example eval_clouds -- A B --raw --distances`, and compares per-point
nearest-neighbour distances, accuracy/completeness (mean and median) and precision/recall/F-score with
`scipy.spatial.cKDTree` (to 1e-6; inlier counts must match exactly). Then it writes two PNGs and compares
`--example image_metrics` (PSNR, SSIM) with a SciPy port of scikit-image's `structural_similarity`
(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1, channel_axis=-1), and with
scikit-image itself when it is installed (`--with-skimage` installs it).

Exits non-zero on any disagreement. Usage: ~/.cache/silvr-venv/bin/python scripts/crosscheck_eval.py
[--with-skimage] [--keep] (the virtual environment scripts/setup.sh makes; a plain python3 works where numpy
and scipy are installed).
"""

import json
import os
import struct
import subprocess
import sys
import tempfile
import zlib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TOL = 1e-6
THRESHOLDS = [0.03, 0.05, 0.10, 0.20]


def ensure(module, package):
    """Imports `module`, installing `package` with pip first when this Python is a virtual environment
    (scripts/setup.sh makes one; a system Python refuses or should not get `pip install`, PEP 668)."""
    try:
        return __import__(module)
    except ImportError:
        if sys.prefix == sys.base_prefix:
            sys.exit(
                f"{module} is missing and {sys.executable} is not a virtual environment: run scripts/setup.sh "
                "and this script with its Python (scripts/test.sh does: $SILVR_VENV, default ~/.cache/silvr-venv)"
            )
        print(f"installing {package} with pip ...", flush=True)
        subprocess.check_call([sys.executable, "-m", "pip", "install", "--quiet", package])
        return __import__(module)


ensure("numpy", "numpy")
ensure("scipy", "scipy")
import numpy as np  # noqa: E402
from scipy import ndimage  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

failures = []


def check(name, ok, detail=""):
    status = "ok " if ok else "FAIL"
    print(f"  [{status}] {name} {detail}")
    if not ok:
        failures.append(name)


# ----------------------------------------------------------------------------------------------- PLY


def write_ply_binary_le_double(path, xyz, rgb, intensity, faces):
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment crosscheck\n"
        f"element vertex {len(xyz)}\nproperty double x\nproperty double y\nproperty double z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty float intensity\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    vdt = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("r", "u1"), ("g", "u1"), ("b", "u1"), ("i", "<f4")])
    v = np.empty(len(xyz), dtype=vdt)
    v["x"], v["y"], v["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    v["r"], v["g"], v["b"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    v["i"] = intensity
    with open(path, "wb") as f:
        f.write(header.encode())
        f.write(v.tobytes())
        for face in faces:
            f.write(struct.pack("<B", len(face)) + struct.pack(f"<{len(face)}i", *face))


def write_ply_ascii_float(path, xyz32):
    with open(path, "w") as f:
        f.write(f"ply\nformat ascii 1.0\nelement vertex {len(xyz32)}\n")
        f.write("property float x\nproperty float y\nproperty float z\nend_header\n")
        for p in xyz32:
            # repr of the float32 value widened to float64 round-trips exactly.
            f.write(" ".join(repr(float(c)) for c in p) + "\n")


def write_ply_binary_be_float(path, xyz32):
    header = (
        f"ply\nformat binary_big_endian 1.0\nelement vertex {len(xyz32)}\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    )
    with open(path, "wb") as f:
        f.write(header.encode())
        f.write(xyz32.astype(">f4").tobytes())


def target_dir():
    meta = subprocess.run(["cargo", "metadata", "-q", "--format-version", "1", "--no-deps"], cwd=ROOT,
                          check=True, capture_output=True, text=True)
    return json.loads(meta.stdout)["target_directory"]


def cargo_example(name, *args):
    # The examples built with the whole workspace's feature set (as `cargo test --workspace` builds them):
    # `cargo run -p silvr-core` would resolve features for one package and recompile the engine.
    cmd = [os.path.join(target_dir(), "debug", "examples", name), *args]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if res.returncode != 0:
        print(res.stdout)
        print(res.stderr, file=sys.stderr)
        raise SystemExit(f"{' '.join(cmd)} failed with exit code {res.returncode}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def reference_metrics(rec, gt):
    d_rg = cKDTree(gt).query(rec, k=1)[0]
    d_gr = cKDTree(rec).query(gt, k=1)[0]
    out = {
        "accuracy_m": float(np.mean(d_rg)),
        "completeness_m": float(np.mean(d_gr)),
        "accuracy_median_m": float(np.median(d_rg)),
        "completeness_median_m": float(np.median(d_gr)),
        "thresholds": [],
    }
    for t in THRESHOLDS:
        ni, nj = int(np.sum(d_rg < t)), int(np.sum(d_gr < t))
        p, r = ni / len(rec), nj / len(gt)
        f = 2 * p * r / (p + r) if p + r > 0 else 0.0
        out["thresholds"].append(dict(threshold_m=t, precision=p, recall=r, fscore=f, ni=ni, nj=nj))
    return d_rg, d_gr, out


def compare_clouds(label, rec_path, gt_path, rec, gt):
    print(f"{label}: {os.path.basename(rec_path)} ({len(rec)} pts) vs {os.path.basename(gt_path)} ({len(gt)} pts)")
    ours = cargo_example(
        "eval_clouds", rec_path, gt_path, "--raw", "--distances", "--thresholds", ",".join(map(str, THRESHOLDS))
    )
    d_rg, d_gr, ref = reference_metrics(rec, gt)
    rep = ours["report"]
    our_rg, our_gr = np.array(ours["rec_to_gt"]), np.array(ours["gt_to_rec"])
    check("rec->gt distance count", len(our_rg) == len(d_rg), f"{len(our_rg)} vs {len(d_rg)}")
    check("gt->rec distance count", len(our_gr) == len(d_gr), f"{len(our_gr)} vs {len(d_gr)}")
    if len(our_rg) == len(d_rg) and len(our_gr) == len(d_gr):
        e1, e2 = float(np.max(np.abs(our_rg - d_rg))), float(np.max(np.abs(our_gr - d_gr)))
        check("per-point rec->gt distances", e1 <= TOL, f"max |diff| = {e1:.3e}")
        check("per-point gt->rec distances", e2 <= TOL, f"max |diff| = {e2:.3e}")
    for k in ["accuracy_m", "completeness_m", "accuracy_median_m", "completeness_median_m"]:
        diff = abs(rep[k] - ref[k])
        check(k, diff <= TOL, f"ours {rep[k]:.9f} scipy {ref[k]:.9f}")
    for ours_t, ref_t in zip(rep["thresholds"], ref["thresholds"]):
        t = ref_t["threshold_m"]
        cm = f"{round(t * 100)}cm"
        same_counts = ours_t["reconstruction_inliers"] == ref_t["ni"] and ours_t["gt_inliers"] == ref_t["nj"]
        check(f"inlier counts @{cm}", same_counts,
              f"ours ({ours_t['reconstruction_inliers']}, {ours_t['gt_inliers']}) scipy ({ref_t['ni']}, {ref_t['nj']})")
        for k in ["precision", "recall", "fscore"]:
            flat = rep[f"{k}_{cm}"]
            ok = abs(ours_t[k] - ref_t[k]) <= TOL and abs(flat - ref_t[k]) <= TOL
            check(f"{k}_{cm}", ok, f"ours {ours_t[k]:.9f} scipy {ref_t[k]:.9f}")


# ---------------------------------------------------------------------------------------------- images


def write_png_rgb8(path, img):
    h, w, _ = img.shape
    raw = b"".join(b"\x00" + img[y].astype(np.uint8).tobytes() for y in range(h))

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n")
        f.write(chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)))
        f.write(chunk(b"IDAT", zlib.compress(raw, 9)))
        f.write(chunk(b"IEND", b""))


def ssim_reference(a, b):
    """Port of skimage.metrics.structural_similarity for gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=1, channel_axis=-1."""
    sigma, truncate = 1.5, 3.5
    pad = (2 * int(truncate * sigma + 0.5) + 1 - 1) // 2
    c1, c2 = (0.01 * 1.0) ** 2, (0.03 * 1.0) ** 2
    vals = []
    for c in range(a.shape[2]):
        x, y = a[..., c], b[..., c]

        def filt(im):
            return ndimage.gaussian_filter(im, sigma=sigma, mode="reflect", truncate=truncate)

        ux, uy, uxx, uyy, uxy = filt(x), filt(y), filt(x * x), filt(y * y), filt(x * y)
        vx, vy, vxy = uxx - ux * ux, uyy - uy * uy, uxy - ux * uy
        s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux**2 + uy**2 + c1) * (vx + vy + c2))
        vals.append(s[pad:-pad, pad:-pad].mean(dtype=np.float64))
    return float(np.mean(vals))


def compare_images(tmp, rng, with_skimage):
    print("images: PSNR / SSIM")
    h, w = 48, 64
    yy, xx = np.mgrid[0:h, 0:w]
    base = 128 + 80 * np.sin(xx[..., None] * 0.21 + np.arange(3) * 0.7) * np.cos(yy[..., None] * 0.13)
    a = np.clip(base + rng.normal(0, 12, (h, w, 3)), 0, 255).round().astype(np.uint8)
    b = np.clip(a.astype(float) + rng.normal(0, 20, (h, w, 3)), 0, 255).round().astype(np.uint8)
    pa, pb = os.path.join(tmp, "a.png"), os.path.join(tmp, "b.png")
    write_png_rgb8(pa, a)
    write_png_rgb8(pb, b)
    ours = cargo_example("image_metrics", pa, pb)
    af, bf = a.astype(np.float64) / 255.0, b.astype(np.float64) / 255.0
    mse = np.mean((af - bf) ** 2)
    ref_psnr = float(10 * np.log10(1.0 / mse))
    ref_ssim = ssim_reference(af, bf)
    check("psnr", abs(ours["psnr"] - ref_psnr) <= TOL, f"ours {ours['psnr']:.9f} numpy {ref_psnr:.9f}")
    check("ssim vs scipy port", abs(ours["ssim"] - ref_ssim) <= TOL, f"ours {ours['ssim']:.9f} ref {ref_ssim:.9f}")
    try:
        from skimage.metrics import structural_similarity
    except ImportError:
        if with_skimage:
            subprocess.check_call([sys.executable, "-m", "pip", "install", "--quiet", "scikit-image"])
            from skimage.metrics import structural_similarity
        else:
            print("  (scikit-image not installed: skipped the direct comparison; --with-skimage installs it)")
            return False
    sk = float(structural_similarity(af, bf, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                     data_range=1.0, channel_axis=-1))
    check("ssim vs scikit-image", abs(ours["ssim"] - sk) <= TOL, f"ours {ours['ssim']:.9f} skimage {sk:.9f}")
    return True


def main():
    with_skimage = "--with-skimage" in sys.argv
    keep = "--keep" in sys.argv
    rng = np.random.default_rng(20240517)
    tmp = tempfile.mkdtemp(prefix="silvr-crosscheck-")
    print(f"temp dir: {tmp}")
    print("building examples ...", flush=True)
    subprocess.run(["cargo", "build", "-q", "--workspace", "--examples"], cwd=ROOT, check=True)

    # GT-like cloud: points on a few planes plus scattered points, with exact duplicates (ties).
    n_gt = 6000
    gt = rng.uniform(-2.0, 2.0, (n_gt, 3))
    planes = rng.integers(0, 3, n_gt)
    gt[np.arange(n_gt), planes] = rng.choice([-2.0, 0.0, 2.0], n_gt)
    gt[:300] = gt[300:600]  # duplicates
    gt[600:700] = np.round(gt[600:700], 1)  # quantised coordinates
    # Reconstruction: a noisy subset of the GT plus outliers.
    n_rec = 4500
    pick = rng.choice(n_gt, n_rec - 500, replace=False)
    rec = np.concatenate([gt[pick] + rng.normal(0, 0.04, (n_rec - 500, 3)), rng.uniform(-2.5, 2.5, (500, 3))])
    rgb = rng.integers(0, 256, (n_gt, 3))
    intensity = rng.uniform(0, 1, n_gt).astype(np.float32)
    faces = [rng.integers(0, n_gt, rng.integers(3, 6)).tolist() for _ in range(40)]

    gt_path = os.path.join(tmp, "gt_le_double.ply")
    write_ply_binary_le_double(gt_path, gt, rgb, intensity, faces)
    rec32 = rec.astype(np.float32)
    rec_ascii = os.path.join(tmp, "rec_ascii_float.ply")
    rec_be = os.path.join(tmp, "rec_be_float.ply")
    write_ply_ascii_float(rec_ascii, rec32)
    write_ply_binary_be_float(rec_be, rec32)
    rec64 = rec32.astype(np.float64)

    compare_clouds("ascii float rec vs binary LE double GT", rec_ascii, gt_path, rec64, gt)
    compare_clouds("binary BE float rec vs binary LE double GT", rec_be, gt_path, rec64, gt)
    compare_clouds("swapped roles", gt_path, rec_be, gt, rec64)
    used_skimage = compare_images(tmp, rng, with_skimage)

    if not keep:
        for f in os.listdir(tmp):
            os.remove(os.path.join(tmp, f))
        os.rmdir(tmp)
    if failures:
        print(f"\nCROSS-CHECK FAILED: {len(failures)} disagreement(s): {', '.join(failures)}")
        return 1
    print("\ncross-check passed: silvr-core agrees with SciPy" + (" and scikit-image" if used_skimage else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
