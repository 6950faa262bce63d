#!/usr/bin/env python3
"""The Python `rosbags` package (what robotics people convert bags with) as the independent peer of
`silvr ingest` for ROS 1 `.bag` and ROS 2 `.db3` bags. Test setup only (scripts/setup.sh installs it into the
test virtual environment); never a product dependency.

  rosbags_peer.py convert SRC.mcap --ros1 OUT.bag --db3 OUT_DIR [--zstd file|message]
      Writes every message of an MCAP (ROS 2, CDR) as a ROS 1 bag (messages re-serialised by rosbags from
      its ROS 2 type store, definitions from its ROS 1 store, lz4 chunks) and as a rosbag2 sqlite3 bag (the
      CDR payloads as they are; zstd-compressed per file or per message with --zstd). core/tests/rosbags.rs
      then ingests them all and compares the datasets.
  rosbags_peer.py summary BAG
      Prints {"topics": {topic: {"type": ..., "messages": n}}} as rosbags reads the bag (ROS 1 file or
      rosbag2 folder); topics without messages are left out, as `silvr ingest --info` lists them.
"""
import argparse
import json
import sys
from pathlib import Path


def convert(src, ros1_out, db3_out, zstd=None):
    from mcap.reader import make_reader
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    # The ROS 1 bag's message definitions come from ROS 1's own types (std_msgs/Header with its `seq`),
    # as a ROS 1 recorder writes them; the ROS 2 store's would not match the ROS 1 payloads.
    store1 = get_typestore(Stores.ROS1_NOETIC)
    with open(src, "rb") as f:
        msgs = list(make_reader(f).iter_messages())
    w1 = Writer1(Path(ros1_out))
    w1.set_compression(Writer1.CompressionFormat.LZ4)
    w2 = Writer2(Path(db3_out), version=8, storage_plugin=StoragePlugin.SQLITE3)
    if zstd:
        from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

        mode = {"file": CompressionMode.FILE, "message": CompressionMode.MESSAGE}[zstd]
        w2.set_compression(mode, CompressionFormat.ZSTD)
    conns1, conns2 = {}, {}
    with w1, w2:
        for schema, channel, m in msgs:
            t = schema.name
            if channel.topic not in conns1:
                if t not in store1.fielddefs:
                    # ROS 1 had no tf2_msgs/TFMessage in the noetic store: its first section (the root
                    # type; the types it uses are ROS 1's) from the bag's schema.
                    root = schema.data.decode().split("\n===")[0]
                    store1.register(get_types_from_msg(root, t))
                conns1[channel.topic] = w1.add_connection(channel.topic, t, typestore=store1)
                conns2[channel.topic] = w2.add_connection(channel.topic, t, typestore=store)
            w1.write(conns1[channel.topic], m.log_time, store.cdr_to_ros1(m.data, t))
            w2.write(conns2[channel.topic], m.log_time, m.data)
    print(json.dumps({"messages": len(msgs), "topics": len(conns1)}))


def summary(path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    topics = {}
    with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
        for c in r.connections:
            t = topics.setdefault(c.topic, {"type": c.msgtype, "messages": 0})
            t["messages"] += c.msgcount
    topics = {k: v for k, v in topics.items() if v["messages"] > 0}
    print(json.dumps({"topics": topics}, sort_keys=True))


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("convert")
    c.add_argument("src")
    c.add_argument("--ros1", required=True)
    c.add_argument("--db3", required=True)
    c.add_argument("--zstd", choices=["file", "message"])
    s = sub.add_parser("summary")
    s.add_argument("bag")
    a = p.parse_args()
    if a.cmd == "convert":
        convert(a.src, a.ros1, a.db3, a.zstd)
    else:
        summary(a.bag)


if __name__ == "__main__":
    sys.exit(main())
