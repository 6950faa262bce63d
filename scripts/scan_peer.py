#!/usr/bin/env python3
"""pye57 and laspy (the Python readers survey people use) as the independent peers of `silvr eval --gt`'s
E57 and LAS/LAZ reader (core/tests/scan_gt.rs). Test setup only; never a product dependency.

  scan_peer.py FILE...
      Prints {file: {"points": n, "xyz": [[x, y, z] of every 97th point], "rgb": [[r, g, b] 8-bit ...] or
      null}} as JSON. E57: every scan, each transformed by its pose, invalid points dropped (pye57
      read_scan(transform=True, ignore_missing_fields=True)); LAS/LAZ: laspy's scaled x, y, z and 16-bit
      colours >> 8.
"""
import json
import sys

import numpy as np

STEP = 97


def e57(path):
    import pye57

    f = pye57.E57(path)
    xyz, rgb, has_rgb = [], [], True
    for i in range(f.scan_count):
        try:
            d = f.read_scan(i, transform=True, ignore_missing_fields=True, colors=True)
        except Exception:
            # pye57 reads colours into 8 bits and fails on 16-bit ones (LAStools' las2e57): points only.
            d = f.read_scan(i, transform=True, ignore_missing_fields=True, colors=False)
        p = np.stack([d["cartesianX"], d["cartesianY"], d["cartesianZ"]], axis=1)
        ok = np.isfinite(p).all(axis=1)
        if "cartesianInvalidState" in d:
            ok &= np.asarray(d["cartesianInvalidState"]) == 0
        xyz.append(p[ok])
        if all(k in d for k in ("colorRed", "colorGreen", "colorBlue")):
            rgb.append(np.stack([d["colorRed"], d["colorGreen"], d["colorBlue"]], axis=1)[ok])
        else:
            has_rgb = False
    xyz = np.concatenate(xyz) if xyz else np.zeros((0, 3))
    return xyz, (np.concatenate(rgb) if has_rgb and rgb else None)


def las(path):
    import laspy

    f = laspy.read(path)
    xyz = np.stack([f.x, f.y, f.z], axis=1)
    rgb = None
    if "red" in f.point_format.dimension_names:
        rgb = np.stack([f.red, f.green, f.blue], axis=1).astype(np.int64) >> 8
    return xyz, rgb


def main():
    out = {}
    for path in sys.argv[1:]:
        xyz, rgb = e57(path) if path.endswith(".e57") else las(path)
        out[path] = {
            "points": int(len(xyz)),
            "xyz": xyz[::STEP].tolist(),
            "rgb": None if rgb is None else np.asarray(rgb)[::STEP].astype(int).tolist(),
        }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
