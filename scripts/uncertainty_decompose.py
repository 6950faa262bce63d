#!/usr/bin/env python3
"""Which part of each uncertainty read-out ranks the error (BENCHMARKS.md, "Why depth and colour tie").

Reads a run's `error.ply` (the exported points with `log_std_*`, `depth_spread_m` and `error_m`, as
`silvr demo` writes it) and its `train.json` (the fitted factors k and spread factors a), splits each calibrated
read-out σ = √((k·σ_L)² + (a·s)²) back into the Laplace σ_L and the ray's spread s, and prints the AUSE of
each part, of the read-outs, and of the best (k, a) on a grid (fitted on the ground truth, so an upper bound of
what any calibration could reach), with a lidar noise growing with range as a variant of the depth σ.

    ~/.cache/silvr-venv/bin/python scripts/uncertainty_decompose.py D/silvr D/dataset/transforms.json

Needs numpy and scipy (the crosscheck venv of scripts/setup.sh); analysis only, not a product dependency.
"""
import json
import sys

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import spearmanr

READ_OUTS = ["colour", "depth", "combined"]


def read_ply(path):
    with open(path, "rb") as f:
        props, n = [], 0
        while True:
            line = f.readline().decode().strip()
            if line.startswith("element vertex"):
                n = int(line.split()[2])
            elif line.startswith("property"):
                _, t, name = line.split()
                props.append((name, {"double": "<f8", "float": "<f4", "uchar": "u1"}[t]))
            elif line == "end_header":
                break
        dt = np.dtype(props)
        return np.frombuffer(f.read(n * dt.itemsize), dtype=dt, count=n)


def ause(u, e):
    """Area between the sparsification curve (remove the most uncertain first) and the oracle's, over the
    mean error: 0 is the oracle, ~1 a random order."""
    frac = np.linspace(0.0, 0.99, 100)

    def curve(order):
        return np.array([e[order[int(f * len(e)):]].mean() for f in frac])

    return np.trapezoid(curve(np.argsort(-u)) - curve(np.argsort(-e)), frac) / e.mean()


def main(run_dir, transforms):
    d = read_ply(f"{run_dir}/error.ply")
    brief = json.load(open(f"{run_dir}/train.json"))["uncertainty_brief"]
    k = dict(zip(READ_OUTS, brief["factors"]))
    a = dict(zip(READ_OUTS, brief["spread_factors"]))
    e = d["error_m"].astype(float)
    s = d["depth_spread_m"].astype(float)
    cams = np.array([np.array(f["transform_matrix"])[:3, 3] for f in json.load(open(transforms))["frames"]])
    dist = cKDTree(cams).query(np.stack([d["x"], d["y"], d["z"]], 1))[0]
    print(f"{len(e)} points, median error {np.median(e) * 100:.2f} cm")
    print(f"spread alone: AUSE {ause(s, e):.4f}, Spearman with the error {spearmanr(s, e)[0]:.3f}")
    grid = [(kk, aa) for kk in 10 ** np.arange(-3, 1.01, 0.25) for aa in [0.0, 0.05, 0.1, 0.2, 0.4]]
    for m in READ_OUTS:
        sigma = 10 ** d[f"log_std_{m}"].astype(float)
        laplace = np.sqrt(np.maximum(sigma**2 - (a[m] * s) ** 2, 1e-30)) / k[m]
        best = min((ause(np.sqrt((kk * laplace) ** 2 + (aa * s) ** 2), e), kk, aa) for kk, aa in grid)
        print(
            f"{m}: calibrated {ause(sigma, e):.4f} (k {k[m]:.3g}, a {a[m]:.3g}); Laplace alone "
            f"{ause(laplace, e):.4f} (Spearman with the error {spearmanr(laplace, e)[0]:.3f}, with the camera "
            f"distance {spearmanr(laplace, dist)[0]:.3f}); best on the grid {best[0]:.4f} (k {best[1]:.3g}, a {best[2]})"
        )
        if m == "depth":
            for deg in [0.05, 0.1, 0.2, 0.5]:
                ranged = laplace * np.sqrt(1 + (dist * np.radians(deg) / 0.02) ** 2)
                best = min((ause(np.sqrt((kk * ranged) ** 2 + (aa * s) ** 2), e), kk, aa) for kk, aa in grid)
                print(f"  lidar noise √(2 cm² + (r·{deg}°)²): alone {ause(ranged, e):.4f}, best mix {best[0]:.4f}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
