#!/usr/bin/env python3
"""Helpers of scripts/bench-poses.sh (standard library only; COLMAP's side of the pose benchmark).

    cameras TRANSFORMS OUTDIR        one image list + one `MODEL<TAB>PARAMS` file per camera (COLMAP's pixel
                                     convention is nerfstudio's: cx, cy are copied as they are)
    masks TRANSFORMS OUTDIR          sky masks (255 = sky) -> COLMAP masks (0 = no features), OUTDIR/NAME.png
    prior DB EXPORT_DIR OUTDIR       `silvr export colmap` of the prior -> a model with the database's
                                     camera and image ids, empty keypoint lines, no points (point_triangulator input)
    centres TRANSFORMS OUT           model_aligner reference: "NAME X Y Z" camera centres of a transforms.json
    dbstats DB                       features and verified matches in a COLMAP database (JSON)
    reproj MODEL_DIR                 reprojection RMSE / mean / observations / points of a COLMAP text model (JSON),
                                     one formula for every model (PINHOLE, OPENCV, OPENCV_FISHEYE)
    summary WORK OUT                 the table and the JSON summary
"""

import json
import math
import os
import sqlite3
import struct
import sys
import zlib
from collections import OrderedDict


def frames_of(transforms):
    with open(transforms) as f:
        root = json.load(f)
    shared = {k: root[k] for k in ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_model",
                                   "k1", "k2", "k3", "k4", "p1", "p2") if k in root}
    out = []
    for fr in root["frames"]:
        g = dict(shared)
        g.update(fr)
        out.append(g)
    return out


def camera_of(fr):
    return fr.get("camera") or os.path.dirname(fr["file_path"])


def colmap_camera(fr):
    """COLMAP model name and parameters of a nerfstudio frame (cx, cy already in COLMAP's convention)."""
    m = fr.get("camera_model", "OPENCV")
    g = lambda k: float(fr.get(k, 0.0))
    base = [g("fl_x"), g("fl_y"), g("cx"), g("cy")]
    if m == "OPENCV_FISHEYE":
        return m, base + [g("k1"), g("k2"), g("k3"), g("k4")]
    if m in ("PINHOLE", "SIMPLE_PINHOLE"):
        return "PINHOLE", base
    if m == "OPENCV":
        if g("k3") != 0.0:
            return "FULL_OPENCV", base + [g("k1"), g("k2"), g("p1"), g("p2"), g("k3"), 0.0, 0.0, 0.0]
        return m, base + [g("k1"), g("k2"), g("p1"), g("p2")]
    raise SystemExit(f"unsupported camera_model {m}")


def cmd_cameras(transforms, outdir):
    os.makedirs(outdir, exist_ok=True)
    groups = OrderedDict()
    for fr in frames_of(transforms):
        groups.setdefault(camera_of(fr), []).append(fr)
    for cam, frs in groups.items():
        model, params = colmap_camera(frs[0])
        for fr in frs[1:]:
            if colmap_camera(fr) != (model, params):
                raise SystemExit(f"camera {cam}: frames with different intrinsics")
        safe = cam.replace("/", "_") or "camera"
        with open(os.path.join(outdir, safe + ".list"), "w") as f:
            f.write("".join(fr["file_path"] + "\n" for fr in frs))
        with open(os.path.join(outdir, safe + ".params"), "w") as f:
            f.write(model + "\t" + ",".join(repr(p) for p in params) + "\n")
        print(safe)


# --- PNG (8-bit, non-interlaced) -------------------------------------------------------------------------

def png_read_grey(path):
    data = open(path, "rb").read()
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError("not a PNG")
    pos, idat, hdr = 8, [], None
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos:pos + 4])
        kind = data[pos + 4:pos + 8]
        body = data[pos + 8:pos + 8 + n]
        pos += 12 + n
        if kind == b"IHDR":
            hdr = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
    w, h, depth, ctype, _, _, interlace = hdr
    channels = {0: 1, 2: 3, 4: 2, 6: 4}.get(ctype)
    if depth != 8 or channels is None or interlace != 0:
        raise ValueError(f"unsupported PNG (depth {depth}, colour type {ctype}, interlace {interlace})")
    raw = zlib.decompress(b"".join(idat))
    bpp, stride = channels, w * channels
    prev = bytearray(stride)
    grey = bytearray(w * h)
    for y in range(h):
        ft = raw[y * (stride + 1)]
        line = bytearray(raw[y * (stride + 1) + 1:(y + 1) * (stride + 1)])
        for i in range(stride):
            a = line[i - bpp] if i >= bpp else 0
            b = prev[i]
            c = prev[i - bpp] if i >= bpp else 0
            if ft == 1:
                line[i] = (line[i] + a) & 255
            elif ft == 2:
                line[i] = (line[i] + b) & 255
            elif ft == 3:
                line[i] = (line[i] + ((a + b) >> 1)) & 255
            elif ft == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pr = a if (pa <= pb and pa <= pc) else (b if pb <= pc else c)
                line[i] = (line[i] + pr) & 255
        grey[y * w:(y + 1) * w] = line[0::channels]
        prev = line
    return w, h, grey


def png_write_grey(path, w, h, grey):
    def chunk(kind, body):
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)
    raw = b"".join(b"\x00" + bytes(grey[y * w:(y + 1) * w]) for y in range(h))
    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
                + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


def cmd_masks(transforms, outdir):
    root = os.path.dirname(os.path.abspath(transforms))
    n = sky = 0
    for fr in frames_of(transforms):
        rel = fr.get("sky_mask_path")
        if not rel:
            continue
        w, h, m = png_read_grey(os.path.join(root, rel))
        keep = bytearray(0 if v >= 128 else 255 for v in m)
        sky += sum(1 for v in keep if v == 0)
        out = os.path.join(outdir, fr["file_path"] + ".png")
        os.makedirs(os.path.dirname(out), exist_ok=True)
        png_write_grey(out, w, h, keep)
        n += 1
    print(json.dumps({"masks": n, "sky_fraction": sky / max(1, n * w * h) if n else 0.0}))


# --- models -----------------------------------------------------------------------------------------------

MODEL_NAMES = {0: "SIMPLE_PINHOLE", 1: "PINHOLE", 2: "SIMPLE_RADIAL", 3: "RADIAL", 4: "OPENCV",
               5: "OPENCV_FISHEYE", 6: "FULL_OPENCV"}


def read_images_txt(path):
    """(first line tokens, second line) per image."""
    lines = [l.rstrip("\n") for l in open(path)]
    out, i = [], 0
    while i < len(lines):
        l = lines[i]
        if not l.strip() or l.startswith("#"):
            i += 1
            continue
        out.append((l.split(None, 9), lines[i + 1] if i + 1 < len(lines) else ""))
        i += 2
    return out


def cmd_prior(db, export_dir, outdir):
    os.makedirs(outdir, exist_ok=True)
    con = sqlite3.connect(db)
    cams = con.execute("select camera_id, model, width, height, params from cameras order by camera_id").fetchall()
    ids = {name: (iid, cid) for iid, name, cid in con.execute("select image_id, name, camera_id from images")}
    with open(os.path.join(outdir, "cameras.txt"), "w") as f:
        for cid, model, w, h, blob in cams:
            params = struct.unpack("<%dd" % (len(blob) // 8), blob)
            f.write(f"{cid} {MODEL_NAMES[model]} {w} {h} " + " ".join(repr(p) for p in params) + "\n")
    missing = []
    with open(os.path.join(outdir, "images.txt"), "w") as f:
        for toks, _ in read_images_txt(os.path.join(export_dir, "images.txt")):
            name = toks[9]
            if name not in ids:
                missing.append(name)
                continue
            iid, cid = ids[name]
            f.write(" ".join([str(iid)] + toks[1:8] + [str(cid), name]) + "\n\n")
    open(os.path.join(outdir, "points3D.txt"), "w").close()
    if missing:
        raise SystemExit(f"{len(missing)} prior images are not in the database, e.g. {missing[0]}")
    print(len(ids))


def cmd_centres(transforms, out):
    with open(out, "w") as f:
        for fr in frames_of(transforms):
            m = fr["transform_matrix"]
            f.write(f"{fr['file_path']} {m[0][3]!r} {m[1][3]!r} {m[2][3]!r}\n")


def cmd_dbstats(db):
    con = sqlite3.connect(db)
    q = lambda s: con.execute(s).fetchone()[0] or 0
    images = q("select count(*) from images")
    print(json.dumps({
        "images": images,
        "features": q("select sum(rows) from keypoints"),
        "features_per_image": q("select sum(rows) from keypoints") / max(1, images),
        "pairs_matched": q("select count(*) from matches where rows > 0"),
        "pairs_verified": q("select count(*) from two_view_geometries where rows > 0"),
        "matches_verified": q("select sum(rows) from two_view_geometries"),
    }))


def project(model, p, X):
    x, y, z = X
    if z <= 1e-12:
        return None
    fx, fy, cx, cy = p[:4]
    u, v = x / z, y / z
    if model == "OPENCV_FISHEYE":
        k1, k2, k3, k4 = p[4:8]
        r = math.hypot(u, v)
        if r > 1e-12:
            th = math.atan(r)
            t2 = th * th
            thd = th * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
            u, v = u * thd / r, v * thd / r
    elif model in ("OPENCV", "FULL_OPENCV"):
        k1, k2, p1, p2 = p[4:8]
        k3 = p[8] if model == "FULL_OPENCV" else 0.0
        r2 = u * u + v * v
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        u, v = (u * rad + 2 * p1 * u * v + p2 * (r2 + 2 * u * u),
                v * rad + p1 * (r2 + 2 * v * v) + 2 * p2 * u * v)
    elif model == "SIMPLE_PINHOLE":
        fx, cx, cy = p[0], p[1], p[2]
        fy = fx
    elif model != "PINHOLE":
        raise SystemExit(f"reproj: camera model {model} not handled")
    return fx * u + cx, fy * v + cy


def quat_rot(q, v):
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    # v + 2 w (q x v) + 2 q x (q x v)
    cx_ = y * v[2] - z * v[1]
    cy_ = z * v[0] - x * v[2]
    cz_ = x * v[1] - y * v[0]
    return (v[0] + 2 * (w * cx_ + y * cz_ - z * cy_),
            v[1] + 2 * (w * cy_ + z * cx_ - x * cz_),
            v[2] + 2 * (w * cz_ + x * cy_ - y * cx_))


def cmd_reproj(d):
    cams = {}
    for l in open(os.path.join(d, "cameras.txt")):
        if l.strip() and not l.startswith("#"):
            t = l.split()
            cams[t[0]] = (t[1], [float(x) for x in t[4:]])
    pts = {}
    for l in open(os.path.join(d, "points3D.txt")):
        if l.strip() and not l.startswith("#"):
            t = l.split()
            pts[t[0]] = (float(t[1]), float(t[2]), float(t[3]))
    sq, ab, n, behind = 0.0, 0.0, 0, 0
    images = read_images_txt(os.path.join(d, "images.txt"))
    for toks, second in images:
        q = [float(x) for x in toks[1:5]]
        t = [float(x) for x in toks[5:8]]
        model, params = cams[toks[8]]
        kp = second.split()
        for k in range(0, len(kp) - 2, 3):
            pid = kp[k + 2]
            if pid == "-1" or pid not in pts:
                continue
            Xc = quat_rot(q, pts[pid])
            Xc = (Xc[0] + t[0], Xc[1] + t[1], Xc[2] + t[2])
            uv = project(model, params, Xc)
            if uv is None:
                behind += 1
                continue
            e2 = (uv[0] - float(kp[k])) ** 2 + (uv[1] - float(kp[k + 1])) ** 2
            sq += e2
            ab += math.sqrt(e2)
            n += 1
    print(json.dumps({"images": len(images), "points": len(pts), "observations": n, "behind": behind,
                      "rmse_px": math.sqrt(sq / n) if n else None, "mean_px": ab / n if n else None}))


# --- summary ----------------------------------------------------------------------------------------------

def load(path, default=None):
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError):
        return default


def cmd_summary(work, out):
    s = load(os.path.join(work, "meta.json"), {})
    times = {}
    for l in open(os.path.join(work, "times.tsv")):
        name, sec, rss, cpu, rc = l.rstrip("\n").split("\t")
        times[name] = {"s": float(sec), "max_rss_mb": float(rss) / 1024 if rss else None,
                       "cpu_percent": float(cpu) if cpu else None, "rc": int(rc)}
    feats = [k for k in times if k.startswith("colmap_features_")]
    if feats:
        times["colmap_features"] = {
            "s": sum(times[k]["s"] for k in feats),
            "max_rss_mb": max((times[k]["max_rss_mb"] or 0) for k in feats),
            "cpu_percent": None, "rc": max(times[k]["rc"] for k in feats)}
    ours_report = load(os.path.join(work, "ours", "report.json"), {})
    p = ours_report.get("poses", {})
    stage = lambda n: times.get(n, {}).get("s")
    prior_stages = OrderedDict((k, stage(k)) for k in (
        "colmap_features", "pairs", "colmap_matches_importer", "colmap_point_triangulator",
        "colmap_bundle_adjuster", "colmap_model_aligner", "colmap_model_converter") if k in times)
    free_stages = OrderedDict((k, stage(k)) for k in (
        "colmap_features", "pairs", "colmap_matches_importer", "colmap_mapper",
        "colmap_free_model_aligner", "colmap_free_model_converter") if k in times)
    total = lambda st: sum(v for v in st.values() if v is not None)
    methods = OrderedDict()
    methods["prior"] = {"errors": load(os.path.join(work, "eval_prior.json"))}
    methods["ours"] = {
        "errors": load(os.path.join(work, "eval_ours.json")),
        "stages_s": OrderedDict((x["stage"], x["seconds"]) for x in p.get("stages", [])),
        "total_s": stage("ours"),
        "max_rss_mb": times.get("ours", {}).get("max_rss_mb"),
        "cpu_percent": times.get("ours", {}).get("cpu_percent"),
        "report_rmse_px": p.get("rmse_px"),
        "reproj": load(os.path.join(work, "reproj_ours.json")),
        "analyzer_mean_px": s.get("analyzer_ours"),
        "points": p.get("points"),
        "registered": p.get("registered"),
        "images": p.get("images"),
    }
    methods["colmap_prior"] = {
        "errors": load(os.path.join(work, "eval_colmap_prior.json")),
        "stages_s": prior_stages,
        "total_s": total(prior_stages),
        "max_rss_mb": max((times[k]["max_rss_mb"] or 0) for k in prior_stages) if prior_stages else None,
        "reproj": load(os.path.join(work, "reproj_colmap_prior.json")),
        "analyzer_mean_px": s.get("analyzer_colmap_prior"),
        "db": load(os.path.join(work, "dbstats.json")),
    }
    if "colmap_mapper" in times:
        methods["colmap_free"] = {
            "errors": load(os.path.join(work, "eval_colmap_free.json")),
            "stages_s": free_stages,
            "total_s": total(free_stages),
            "max_rss_mb": max((times[k]["max_rss_mb"] or 0) for k in free_stages),
            "mapper_rc": times["colmap_mapper"]["rc"],
            "reproj": load(os.path.join(work, "reproj_colmap_free.json")),
            "analyzer_mean_px": s.get("analyzer_colmap_free"),
        }
    summary = OrderedDict(meta=s, times=times, methods=methods)
    ours_t, cp_t = methods["ours"]["total_s"], methods["colmap_prior"]["total_s"]
    summary["speedup_vs_colmap_prior"] = cp_t / ours_t if ours_t else None
    if "colmap_free" in methods and ours_t:
        summary["speedup_vs_colmap_free"] = methods["colmap_free"]["total_s"] / ours_t
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    with open(out, "w") as f:
        json.dump(summary, f, indent=2)

    # The table.
    def fmt(v, spec):
        return "-" if v is None else format(v, spec)
    cols = list(methods)
    rows = []
    err = lambda m, k: (methods[m]["errors"] or {}).get(k)
    frames = (methods["prior"]["errors"] or {}).get("frames")

    def reg(m):
        e = methods[m]["errors"]
        if e:
            return f"{e['registered']}/{e['frames']}"
        r = methods[m].get("reproj")
        return f"{r['images']}/{frames}" if r else "-"
    rows.append(("registered", [reg(m) for m in cols]))
    rows.append(("ATE RMSE (mm)", [fmt(err(m, "ate_rmse_m") and err(m, "ate_rmse_m") * 1e3, ".2f") for m in cols]))
    rows.append(("ATE max (mm)", [fmt(err(m, "ate_max_m") and err(m, "ate_max_m") * 1e3, ".2f") for m in cols]))
    rows.append(("rotation RMSE (deg)", [fmt(err(m, "rot_rmse_deg"), ".3f") for m in cols]))
    rows.append(("RPE trans (mm/step)", [fmt(err(m, "rpe_trans_rmse_m") and err(m, "rpe_trans_rmse_m") * 1e3, ".2f") for m in cols]))
    rows.append(("RPE rot (deg/step)", [fmt(err(m, "rpe_rot_rmse_deg"), ".3f") for m in cols]))
    rr = lambda m, k: (methods[m].get("reproj") or {}).get(k)
    rows.append(("reproj RMSE (px)", [fmt(rr(m, "rmse_px"), ".3f") for m in cols]))
    rows.append(("reproj mean (px, analyzer)", [fmt(methods[m].get("analyzer_mean_px"), ".3f") for m in cols]))
    rows.append(("points", [fmt(rr(m, "points"), "d") for m in cols]))
    rows.append(("observations", [fmt(rr(m, "observations"), "d") for m in cols]))
    rows.append(("total time (s)", [fmt(methods[m].get("total_s"), ".1f") for m in cols]))
    w0 = max(len(r[0]) for r in rows)
    print("\n" + " " * w0 + "  " + "  ".join(f"{c:>14}" for c in cols))
    for name, vals in rows:
        print(f"{name:<{w0}}  " + "  ".join(f"{v:>14}" for v in vals))
    print("\nstages (s):")
    print("  ours:         " + ", ".join(f"{k} {v:.2f}" for k, v in methods["ours"]["stages_s"].items()))
    print("  colmap_prior: " + ", ".join(f"{k.replace('colmap_', '')} {v:.2f}" for k, v in prior_stages.items()))
    if "colmap_free" in methods:
        print("  colmap_free:  " + ", ".join(f"{k.replace('colmap_', '')} {v:.2f}" for k, v in free_stages.items()))
    if summary["speedup_vs_colmap_prior"]:
        print(f"\nspeed: ours {ours_t:.1f} s vs COLMAP with prior {cp_t:.1f} s = {summary['speedup_vs_colmap_prior']:.2f}x")
    print(f"wrote {out}")


def main():
    cmd, args = sys.argv[1], sys.argv[2:]
    {"cameras": cmd_cameras, "masks": cmd_masks, "prior": cmd_prior, "centres": cmd_centres,
     "dbstats": cmd_dbstats, "reproj": cmd_reproj, "summary": cmd_summary}[cmd](*args)


if __name__ == "__main__":
    main()
