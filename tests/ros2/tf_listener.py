"""Listens to `/tf` as a ROS 2 node over rmw_zenoh would and prints every transform.

No ROS installation: samples on rmw_zenoh's key for `tf2_msgs/msg/TFMessage` on `--domain` are
decoded with rosbags' CDR deserialiser (Jazzy type store), independent of factord's encoder.
Prints `ready` once subscribed, then one JSON line per transform:
`{"parent", "child", "stamp_ns", "translation": [x, y, z], "rotation": [x, y, z, w]}`.
Runs until `--seconds` pass or its standard input closes.
"""

import argparse
import json
import sys
import threading

import zenoh
from rosbags.typesys import Stores, get_typestore

STORE = get_typestore(Stores.ROS2_JAZZY)
TF = "tf2_msgs/msg/TFMessage"


def dds_name(msgtype):
    pkg, kind, name = msgtype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--zenoh", required=True)
    parser.add_argument("--domain", type=int, default=0)
    parser.add_argument("--topic", default="/tf")
    parser.add_argument("--seconds", type=float, default=60.0)
    args = parser.parse_args()
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", json.dumps([args.zenoh]))
    config.insert_json5("listen/endpoints", "[]")
    config.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(config)
    key = f"{args.domain}/{args.topic.strip('/')}/{dds_name(TF)}/{STORE.hash_rihs01(TF)}"
    lock = threading.Lock()

    def on_sample(sample):
        message = STORE.deserialize_cdr(bytes(sample.payload.to_bytes()), TF)
        lines = []
        for t in message.transforms:
            stamp = t.header.stamp
            lines.append(json.dumps({
                "parent": t.header.frame_id,
                "child": t.child_frame_id,
                "stamp_ns": int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec),
                "translation": [t.transform.translation.x, t.transform.translation.y,
                                t.transform.translation.z],
                "rotation": [t.transform.rotation.x, t.transform.rotation.y,
                             t.transform.rotation.z, t.transform.rotation.w],
            }))
        with lock:
            for line in lines:
                print(line)
            sys.stdout.flush()

    subscriber = session.declare_subscriber(key, on_sample)
    print("ready", key)
    sys.stdout.flush()
    done = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
    done.wait(args.seconds)
    subscriber.undeclare()
    session.close()


if __name__ == "__main__":
    main()
