#!/usr/bin/env python3
"""Independent decode of a bag written by `silvr synth --mcap` (our MCAP writer, CDR encoders and ros2msg
schema texts), with the reference Python stack (mcap + mcap-ros2-support, which parses the schema text
stored in the file). Prints per-topic counts and spot values as JSON and exits non-zero if any message
fails to decode or a value is implausible.

Usage:
    python3 -m venv /tmp/pyenv && /tmp/pyenv/bin/pip install mcap-ros2-support
    silvr synth --preset ci --out /tmp/s --mcap /tmp/scene.mcap
    /tmp/pyenv/bin/python scripts/crosscheck_bag_writer.py /tmp/scene.mcap
"""
import json
import struct
import sys

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory


def main():
    path = sys.argv[1]
    counts, out = {}, {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        out["profile"] = header.profile
        for schema, channel, message, ros in reader.iter_decoded_messages():
            k = counts.get(channel.topic, 0)
            counts[channel.topic] = k + 1
            if k:
                continue
            if schema.name == "nav_msgs/msg/Odometry":
                p = ros.pose.pose
                out["odometry"] = {
                    "stamp": [ros.header.stamp.sec, ros.header.stamp.nanosec],
                    "frame": ros.header.frame_id, "child": ros.child_frame_id,
                    "t": [p.position.x, p.position.y, p.position.z],
                    "q_xyzw": [p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w],
                }
            elif schema.name == "sensor_msgs/msg/PointCloud2":
                fields = [(fl.name, fl.offset, fl.datatype, fl.count) for fl in ros.fields]
                first = bytes(ros.data[:ros.point_step])
                x, y, z, i = struct.unpack_from("<4f", first, 0)
                ring, = struct.unpack_from("<H", first, 16)
                t, = struct.unpack_from("<d", first, 18)
                out["cloud"] = {"frame": ros.header.frame_id, "width": ros.width, "point_step": ros.point_step,
                                "fields": fields, "first_point": [x, y, z, i, ring, t],
                                "stamp": [ros.header.stamp.sec, ros.header.stamp.nanosec]}
            elif schema.name == "sensor_msgs/msg/CameraInfo":
                out.setdefault("camera_info", {})[ros.header.frame_id] = {
                    "size": [ros.width, ros.height], "model": ros.distortion_model,
                    "d": list(ros.d), "k": list(ros.k)}
            elif schema.name == "sensor_msgs/msg/CompressedImage":
                out.setdefault("images", {})[channel.topic] = {"format": ros.format, "bytes": len(ros.data),
                                                              "png": bytes(ros.data[:8]) == b"\x89PNG\r\n\x1a\n"}
            elif schema.name == "tf2_msgs/msg/TFMessage":
                out["tf_static"] = [(t.header.frame_id, t.child_frame_id,
                                     [t.transform.translation.x, t.transform.translation.y,
                                      t.transform.translation.z]) for t in ros.transforms]
    out["counts"] = counts
    print(json.dumps(out, indent=1))
    ok = (out["profile"] == "ros2" and all(v["png"] for v in out["images"].values())
          and out["cloud"]["point_step"] == 26 and out["cloud"]["first_point"][5] > 1e9
          and len(out["camera_info"]) == 3 and len(out["tf_static"]) == 4)
    if not ok:
        sys.exit("crosscheck failed: see the values above")
    print("our bag decodes with mcap-ros2-support")


if __name__ == "__main__":
    main()
