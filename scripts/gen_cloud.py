#!/usr/bin/env python3
"""A generated map-like cloud of N points as a binary PLY with the fields `points.ply` carries.

For benchmarks of `silvr export copc` and the studio at scale (issue 36): a 140 m x 140 m block (about
20,000 m^2, the paper-scale mission's area) of ground, building walls on a grid, and poles; RGB by surface;
log_std_* (log10 sigma in metres) lognormal around 1-2 cm with a heavier tail on walls far from the
block's centre; a submap index by 35 m tile. Deterministic for a seed; written in chunks of 1 M points,
so memory stays flat whatever N is.

    python3 scripts/gen_cloud.py 20000000 /tmp/cloud20m.ply [--seed 1]
"""
import argparse
import sys

import numpy as np

DTYPE = np.dtype(
    [
        ("x", "<f8"),
        ("y", "<f8"),
        ("z", "<f8"),
        ("red", "u1"),
        ("green", "u1"),
        ("blue", "u1"),
        ("depth_spread_m", "<f4"),
        ("log_std_colour", "<f4"),
        ("log_std_depth", "<f4"),
        ("log_std_combined", "<f4"),
        ("submap", "<f4"),
    ]
)


def chunk(rng, n):
    out = np.empty(n, DTYPE)
    kind = rng.random(n)
    ground = kind < 0.55
    wall = (kind >= 0.55) & (kind < 0.95)
    pole = kind >= 0.95
    x = rng.uniform(-70.0, 70.0, n)
    y = rng.uniform(-70.0, 70.0, n)
    z = np.zeros(n)
    # Walls: buildings every 20 m, faces on x = const (snapped), height up to 12 m.
    nw = int(wall.sum())
    x[wall] = np.round(x[wall] / 20.0) * 20.0 + rng.choice([-4.0, 4.0], nw)
    z[wall] = rng.uniform(0.0, 12.0, nw)
    # Poles: 0.1 m radius cylinders every 10 m, 6 m high.
    npl = int(pole.sum())
    a = rng.uniform(0.0, 2 * np.pi, npl)
    x[pole] = np.round(x[pole] / 10.0) * 10.0 + 5.0 + 0.1 * np.cos(a)
    y[pole] = np.round(y[pole] / 10.0) * 10.0 + 5.0 + 0.1 * np.sin(a)
    z[pole] = rng.uniform(0.0, 6.0, npl)
    z[ground] = 0.02 * np.sin(x[ground] * 0.3) + 0.02 * np.cos(y[ground] * 0.2)
    out["x"], out["y"], out["z"] = x, y, z
    base = np.where(ground, 110, np.where(wall, 180, 60))
    out["red"] = np.clip(base + rng.normal(0, 20, n), 0, 255).astype("u1")
    out["green"] = np.clip(base * 0.9 + rng.normal(0, 20, n), 0, 255).astype("u1")
    out["blue"] = np.clip(base * 0.8 + rng.normal(0, 20, n), 0, 255).astype("u1")
    r = np.hypot(x, y)
    mu = -1.9 + 0.006 * r + np.where(wall, 0.15, 0.0)
    out["log_std_colour"] = (mu + rng.normal(0, 0.35, n)).astype("<f4")
    out["log_std_depth"] = (mu - 0.1 + rng.normal(0, 0.3, n)).astype("<f4")
    out["log_std_combined"] = (
        np.minimum(out["log_std_colour"], out["log_std_depth"]) - 0.1
    ).astype("<f4")
    out["depth_spread_m"] = (10.0 ** (mu + 0.6 + rng.normal(0, 0.3, n))).astype("<f4")
    out["submap"] = (np.floor((x + 70.0) / 35.0) * 4 + np.floor((y + 70.0) / 35.0)).astype("<f4")
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("points", type=int)
    ap.add_argument("out")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    props = "".join(
        f"property {'double' if t.str == '<f8' else 'uchar' if t.str == '|u1' else 'float'} {name}\n"
        for name, (t, _) in DTYPE.fields.items()
    )
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment scripts/gen_cloud.py seed "
        f"{a.seed}\nelement vertex {a.points}\n{props}end_header\n"
    )
    with open(a.out, "wb") as f:
        f.write(header.encode())
        left = a.points
        while left > 0:
            n = min(left, 1_000_000)
            f.write(chunk(rng, n).tobytes())
            left -= n
    print(f"wrote {a.points} points to {a.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
