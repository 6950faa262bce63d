#!/usr/bin/env python3
"""Independent decode of ../shared/data/formats/mcap/nav2_turtlebot.mcap for core/tests/ingest.rs.

Prints, as JSON, per-topic counts, the 1st and 101st nav_msgs/Odometry on /odom, the first
tf2_msgs/TFMessage on /tf and on /tf_static, and the first /amcl_pose, decoded by the reference Python stack (mcap + mcap-ros2-support, which
parses the .msg schema text stored in the file rather than using hand-written layouts).

Usage:
    python3 -m venv /tmp/pyenv && /tmp/pyenv/bin/pip install mcap-ros2-support
    /tmp/pyenv/bin/python scripts/crosscheck_mcap.py [path/to/nav2_turtlebot.mcap]

The Rust test `nav2_turtlebot_matches_python_decoder` hard-codes these values; rerun this script and
update the test if the fixture changes.
"""
import json
import sys
from pathlib import Path

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory


def pose_dict(translation, rotation):
    return {
        "t": [translation.x, translation.y, translation.z],
        "q_xyzw": [rotation.x, rotation.y, rotation.z, rotation.w],
    }


def main():
    default = Path(__file__).resolve().parent.parent / ".." / "shared/data/formats/mcap/nav2_turtlebot.mcap"
    path = Path(sys.argv[1]) if len(sys.argv) > 1 else default
    out = {"file": path.name, "counts": {}}
    counts = out["counts"]
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for index, (schema, channel, message, ros) in enumerate(reader.iter_decoded_messages()):
            k = counts.get(channel.topic, 0)
            counts[channel.topic] = k + 1
            if channel.topic == "/odom" and k in (0, 100):
                p = ros.pose.pose
                out[f"odom_{k}"] = {
                    "index": index,
                    "log_time": message.log_time,
                    "stamp": [ros.header.stamp.sec, ros.header.stamp.nanosec],
                    "frame_id": ros.header.frame_id,
                    "child_frame_id": ros.child_frame_id,
                    "pose": pose_dict(p.position, p.orientation),
                    "covariance0": ros.pose.covariance[0],
                    "twist_linear": [ros.twist.twist.linear.x, ros.twist.twist.linear.y, ros.twist.twist.linear.z],
                    "twist_angular_z": ros.twist.twist.angular.z,
                }
            if channel.topic in ("/tf", "/tf_static") and k == 0:
                out[channel.topic.strip("/")] = {
                    "index": index,
                    "log_time": message.log_time,
                    "transforms": [
                        {
                            "stamp": [t.header.stamp.sec, t.header.stamp.nanosec],
                            "frame_id": t.header.frame_id,
                            "child_frame_id": t.child_frame_id,
                            "transform": pose_dict(t.transform.translation, t.transform.rotation),
                        }
                        for t in ros.transforms
                    ],
                }
            if channel.topic == "/amcl_pose" and k == 0:
                p = ros.pose.pose
                out["amcl_pose_0"] = {
                    "index": index,
                    "frame_id": ros.header.frame_id,
                    "pose": pose_dict(p.position, p.orientation),
                    "covariance": [ros.pose.covariance[0], ros.pose.covariance[7], ros.pose.covariance[35]],
                }
    print(json.dumps(out, indent=2, default=repr))


if __name__ == "__main__":
    main()
