#!/usr/bin/env python3
"""KISS-ICP (the peer of `silvr odometry`, issue 34) on the sweeps `silvr odometry --export-sweeps DIR`
wrote: the same points, the same stamps. Writes a TUM trajectory (T_world_lidar, the first sweep's frame)
and prints JSON with the time per sweep (KissICP.register_frame alone, as ours times its own odometry).

    kiss_icp_peer.py DIR OUT.tum [--deskew] [--max-range 100] [--min-range 0]

Installed by scripts/bench-odometry.sh into its own virtual environment; never a product dependency.
"""
import argparse
import json
import os
import time

import numpy as np

from kiss_icp.config import KISSConfig
from kiss_icp.kiss_icp import KissICP


def quat_xyzw(r):
    """Unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method)."""
    t = np.trace(r)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        return np.array([(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s])
    i = int(np.argmax(np.diag(r)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2.0 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
    q = np.zeros(4)
    q[i] = 0.25 * s
    q[j] = (r[j, i] + r[i, j]) / s
    q[k] = (r[k, i] + r[i, k]) / s
    q[3] = (r[k, j] - r[j, k]) / s
    return q


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dir")
    ap.add_argument("out")
    ap.add_argument("--deskew", action="store_true")
    ap.add_argument("--max-range", type=float, default=100.0)
    ap.add_argument("--min-range", type=float, default=0.0)
    a = ap.parse_args()

    config = KISSConfig()
    config.data.deskew = a.deskew
    config.data.max_range = a.max_range
    config.data.min_range = a.min_range
    config.mapping.voxel_size = a.max_range / 100.0  # what KISS-ICP's config loader derives
    odo = KissICP(config)

    stamps = [float(x) for x in open(os.path.join(a.dir, "stamps.txt")).read().split()]
    lines, seconds = [], []
    for k, stamp in enumerate(stamps):
        rec = np.fromfile(os.path.join(a.dir, f"{k:06d}.bin"), dtype="<f4").reshape(-1, 4).astype(np.float64)
        pts, t = rec[:, :3], rec[:, 3]
        if np.all(np.isfinite(t)):
            lo, hi = t.min(), t.max()
            ref = stamp + 0.5 * (lo + hi)
            # KISS-ICP's dataloaders give per-point times normalised to [0, 1] over the sweep; it deskews
            # to the middle.
            norm = (t - lo) / (hi - lo) if hi > lo else np.full_like(t, 0.5)
        else:
            ref = stamp
            # Without point times KISS-ICP's KITTI loader uses azimuth order.
            norm = 0.5 * (-np.arctan2(pts[:, 1], pts[:, 0]) / np.pi + 1.0)
        t0 = time.perf_counter()
        odo.register_frame(pts, norm)
        seconds.append(time.perf_counter() - t0)
        pose = odo.last_pose
        q = quat_xyzw(pose[:3, :3])
        x, y, z = pose[:3, 3]
        lines.append(f"{ref:.9f} {x:.9f} {y:.9f} {z:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
    with open(a.out + ".tmp", "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n")
    os.replace(a.out + ".tmp", a.out)
    s = sorted(seconds)
    print(json.dumps({
        "sweeps": len(stamps),
        "ms_per_sweep_median": 1e3 * s[len(s) // 2],
        "ms_per_sweep_mean": 1e3 * sum(s) / len(s),
        "deskew": a.deskew,
    }))


if __name__ == "__main__":
    main()
