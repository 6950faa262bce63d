#!/usr/bin/env python3
"""Writes the small third-party-encoded fixtures of core/tests/ingest.rs into core/tests/data/ingest/.

- `py_ros2_lz4.mcap`: ROS 2 messages serialised by mcap-ros2-support (it encodes from the .msg text,
  independently of our hand-written CDR), in lz4-compressed chunks (the shared fixtures have only zstd
  and uncompressed chunks).
- `pypcd4_binary_compressed.pcd`: a PCD written by pypcd4 (PCL-compatible LZF via python-lzf).

The values are simple formulas that core/tests/ingest.rs recomputes. Usage:
    python3 -m venv /tmp/pyenv && /tmp/pyenv/bin/pip install mcap-ros2-support lz4 pypcd4
    /tmp/pyenv/bin/python scripts/make_ingest_fixtures.py
"""
import math
import struct
import zlib
from pathlib import Path

import numpy as np
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer
from pypcd4 import Encoding, PointCloud

OUT = Path(__file__).resolve().parent.parent / "core/tests/data/ingest"
SEP = "=" * 80

TIME = "int32 sec\nuint32 nanosec\n"
HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
VEC3 = "float64 x\nfloat64 y\nfloat64 z\n"
QUAT = "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"


def deps(*pairs):
    return "".join(f"{SEP}\nMSG: {name}\n{text}" for name, text in pairs)


STD = [("std_msgs/Header", HEADER), ("builtin_interfaces/Time", TIME)]
POSE = [("geometry_msgs/Pose", "Point position\nQuaternion orientation\n"),
        ("geometry_msgs/Point", VEC3), ("geometry_msgs/Quaternion", QUAT)]

MSGDEFS = {
    "sensor_msgs/msg/PointCloud2": "std_msgs/Header header\nuint32 height\nuint32 width\nPointField[] fields\n"
    "bool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n"
    + deps(*STD, ("sensor_msgs/PointField", "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\n"
                  "uint8 INT32=5\nuint8 UINT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\n"
                  "string name\nuint32 offset\nuint8 datatype\nuint32 count\n")),
    "sensor_msgs/msg/Image": "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
    "uint8 is_bigendian\nuint32 step\nuint8[] data\n" + deps(*STD),
    "sensor_msgs/msg/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n" + deps(*STD),
    "sensor_msgs/msg/CameraInfo": "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
    "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\n"
    "RegionOfInterest roi\n"
    + deps(*STD, ("sensor_msgs/RegionOfInterest",
                  "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n")),
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms\n"
    + deps(("geometry_msgs/TransformStamped", "std_msgs/Header header\nstring child_frame_id\nTransform transform\n"),
           *STD, ("geometry_msgs/Transform", "Vector3 translation\nQuaternion rotation\n"),
           ("geometry_msgs/Vector3", VEC3), ("geometry_msgs/Quaternion", QUAT)),
    "nav_msgs/msg/Path": "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses\n"
    + deps(*STD, ("geometry_msgs/PoseStamped", "std_msgs/Header header\nPose pose\n"), *POSE),
}


def header(sec, nsec, frame):
    return {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": frame}


def tiny_png():
    """A 2x2 RGB PNG: red, green / blue, white."""
    rows = [bytes([0, 255, 0, 0, 0, 255, 0]), bytes([0, 0, 0, 255, 255, 255, 255])]
    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)
    ihdr = struct.pack(">IIBBBBB", 2, 2, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"".join(rows))) + chunk(b"IEND", b"")


def write_mcap():
    with open(OUT / "py_ros2_lz4.mcap", "wb") as f:
        w = Writer(f, chunk_size=2048, compression=CompressionType.LZ4)
        s = {k: w.register_msgdef(k, v) for k, v in MSGDEFS.items()}
        t0 = 1_700_000_000
        # Hesai layout: x y z intensity f32, ring u16 @16, timestamp f64 @18 (unaligned), point_step 26.
        data = bytearray()
        for k in range(6):
            x = math.nan if k == 3 else 1.0 + k
            data += struct.pack("<ffffHd", x, -0.5 * k, 0.25, 10.0 * k, k % 2, t0 + 0.5 + 0.01 * k)
        fields = [{"name": n, "offset": o, "datatype": d, "count": 1} for n, o, d in
                  [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7), ("ring", 16, 4), ("timestamp", 18, 8)]]
        w.write_message("/hesai/pandar", s["sensor_msgs/msg/PointCloud2"], {
            "header": header(t0, 500_000_000, "hesai_lidar"), "height": 1, "width": 6, "fields": fields,
            "is_bigendian": False, "point_step": 26, "row_step": 156, "data": bytes(data), "is_dense": False},
            log_time=t0 * 10**9 + 500_000_000)
        w.write_message("/cam0/image_raw", s["sensor_msgs/msg/Image"], {
            "header": header(t0, 600_000_000, "cam0"), "height": 2, "width": 2, "encoding": "bgr8",
            "is_bigendian": 0, "step": 6, "data": bytes([0, 0, 255, 0, 255, 0, 255, 0, 0, 255, 255, 255])},
            log_time=t0 * 10**9 + 600_000_000)
        w.write_message("/cam0/image_raw/compressed", s["sensor_msgs/msg/CompressedImage"], {
            "header": header(t0, 600_000_000, "cam0"), "format": "rgb8; png compressed rgb8", "data": tiny_png()},
            log_time=t0 * 10**9 + 600_000_001)
        w.write_message("/cam0/camera_info", s["sensor_msgs/msg/CameraInfo"], {
            "header": header(t0, 600_000_000, "cam0"), "height": 540, "width": 720, "distortion_model": "equidistant",
            "d": [-0.041142, -0.002422, 0.0034, -0.001852],
            "k": [349.1, 0.0, 356.4, 0.0, 349.2, 280.3, 0.0, 0.0, 1.0],
            "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            "p": [349.1, 0.0, 356.4, 0.0, 0.0, 349.2, 280.3, 0.0, 0.0, 0.0, 1.0, 0.0],
            "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}},
            log_time=t0 * 10**9 + 600_000_002)
        w.write_message("/tf_static", s["tf2_msgs/msg/TFMessage"], {"transforms": [
            {"header": header(0, 0, "base_link"), "child_frame_id": "hesai_lidar",
             "transform": {"translation": {"x": 0.0, "y": 0.0, "z": 0.124},
                           "rotation": {"x": 0.0, "y": 0.0, "z": 1.0, "w": 0.0}}},
            {"header": header(0, 0, "hesai_lidar"), "child_frame_id": "cam0",
             "transform": {"translation": {"x": 0.00035, "y": -0.07957, "z": -0.05383},
                           "rotation": {"x": 0.50347, "y": 0.50033, "z": -0.49475, "w": 0.50140}}}]},
            log_time=t0 * 10**9)
        w.write_message("/path", s["nav_msgs/msg/Path"], {"header": header(t0, 0, "map"), "poses": [
            {"header": header(t0, k, "map"),
             "pose": {"position": {"x": float(k), "y": 2.0 * k, "z": 0.0},
                      "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}} for k in range(3)]},
            log_time=t0 * 10**9 + 700_000_000)
        w.finish()


def write_pcd():
    n = 40
    k = np.arange(n)
    x = (k * 0.5).astype(np.float32)
    y = (-k * 0.25).astype(np.float32)
    z = (k % 7).astype(np.float32)
    x[5] = np.nan
    intensity = (k * 3).astype(np.float32)
    ring = (k % 4).astype(np.uint16)
    pc = PointCloud.from_points([x, y, z, intensity, ring], ("x", "y", "z", "intensity", "ring"),
                                (np.float32, np.float32, np.float32, np.float32, np.uint16))
    pc.save(OUT / "pypcd4_binary_compressed.pcd", encoding=Encoding.BINARY_COMPRESSED)


if __name__ == "__main__":
    OUT.mkdir(parents=True, exist_ok=True)
    write_mcap()
    write_pcd()
    for p in sorted(OUT.iterdir()):
        print(p.name, p.stat().st_size)
