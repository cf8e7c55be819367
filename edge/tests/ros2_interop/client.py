"""The ROS 2 side of edge/tests/ros2_interop.rs: an independent DDS (Eclipse Cyclone DDS) and an
independent ROS 2 CDR decoder (rosbags, with Humble's message definitions) talk to slag-edge's
ROS 2 node.

Reads one JSON object on stdin:
  {"topics": {"prompt": "rt/ns/node/prompt", "objects": ..., "matches": ..., "markers": ...},
   "prompts": ["...", ...], "expect": N, "timeout_s": 60,
   "http": "http://127.0.0.1:PORT" (optional: also time GET /query for each prompt),
   "late_subscriber": true (optional: after the run, a new subscription must get the last answer)}
Publishes the prompts in order (after the prompt subscription is matched) and collects the
answers until N of each topic arrived (then waits 1 s more for extra samples). Prints one JSON
object on stdout: every sample decoded by rosbags, plus timings.
"""

import json
import os
import sys
import time
import urllib.parse
import urllib.request
from dataclasses import dataclass

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

# vision_msgs 4.x (the Humble release) is not in rosbags' Humble store: its definitions, as
# published in vision_msgs/msg/*.msg.
VISION_MSGS = {
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "vision_msgs/ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"
    ),
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/Detection3D": (
        "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
        "vision_msgs/BoundingBox3D bbox\nstring id\n"
    ),
    "vision_msgs/msg/Detection3DArray": (
        "std_msgs/Header header\nvision_msgs/Detection3D[] detections\n"
    ),
}

ROS_TYPES = {
    "objects": "vision_msgs/msg/Detection3DArray",
    "matches": "sensor_msgs/msg/PointCloud2",
    "markers": "visualization_msgs/msg/MarkerArray",
}


@dataclass
class String_(IdlStruct, typename="std_msgs::msg::dds_::String_"):
    data: str


class RawSample(bytes):
    """A sample's CDR bytes (Cyclone attaches its `sample_info`)."""


def raw_type(dds_name):
    """A Cyclone topic type named like the ROS type whose samples come back as raw CDR bytes,
    so that rosbags (not Cyclone) decodes them."""

    @dataclass
    class Raw(IdlStruct, typename=dds_name):
        unused: int = 0

        @classmethod
        def deserialize(cls, data, has_header=True, use_version_2=None):
            return RawSample(data)

    return Raw


def dds_type(ros_type):
    pkg, _, name = ros_type.split("/")
    return f"{pkg}::msg::dds_::{name}_"


def header(h):
    return {"stamp": [h.stamp.sec, h.stamp.nanosec], "frame_id": h.frame_id}


def point(p):
    return [p.x, p.y, p.z]


def pose(p):
    o = p.orientation
    return {"position": point(p.position), "orientation": [o.x, o.y, o.z, o.w]}


def decode_objects(m):
    return {
        "header": header(m.header),
        "detections": [
            {
                "header": header(d.header),
                "id": d.id,
                "results": [
                    {
                        "class_id": r.hypothesis.class_id,
                        "score": r.hypothesis.score,
                        "pose": pose(r.pose.pose),
                    }
                    for r in d.results
                ],
                "bbox": {"center": pose(d.bbox.center), "size": point(d.bbox.size)},
            }
            for d in m.detections
        ],
    }


def decode_cloud(m):
    """Points from the fields' own names, offsets and types (FLOAT32 = 7 only)."""
    import struct

    order = ">" if m.is_bigendian else "<"
    fields = {f.name: (f.offset, f.datatype, f.count) for f in m.fields}
    for name in ("x", "y", "z", "score"):
        assert fields[name][1:] == (7, 1), (name, fields[name])
    data = bytes(m.data)
    assert len(data) == m.row_step * m.height, (len(data), m.row_step, m.height)
    points = []
    for i in range(m.width * m.height):
        base = i * m.point_step
        points.append(
            [
                struct.unpack_from(order + "f", data, base + fields[n][0])[0]
                for n in ("x", "y", "z", "score")
            ]
        )
    return {
        "header": header(m.header),
        "height": m.height,
        "width": m.width,
        "point_step": m.point_step,
        "is_dense": bool(m.is_dense),
        "points": points,
    }


def decode_markers(m):
    return {
        "markers": [
            {
                "header": header(k.header),
                "ns": k.ns,
                "id": k.id,
                "type": k.type,
                "action": k.action,
                "pose": pose(k.pose),
                "scale": point(k.scale),
                "text": k.text,
            }
            for k in m.markers
        ]
    }


DECODE = {"objects": decode_objects, "matches": decode_cloud, "markers": decode_markers}


def main():
    req = json.load(sys.stdin)
    topics = req["topics"]
    expect = req["expect"]
    deadline = time.monotonic() + req.get("timeout_s", 60)

    store = get_typestore(Stores.ROS2_HUMBLE)
    types = {}
    for name, text in VISION_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)

    # The domain is ROS_DOMAIN_ID (as rmw_cyclonedds_cpp reads it), the transport CYCLONEDDS_URI.
    dp = DomainParticipant(int(os.environ.get("ROS_DOMAIN_ID", "0")))
    cdr1 = Policy.DataRepresentation(use_cdrv0_representation=True)
    reliable = Policy.Reliability.Reliable(duration(seconds=1))
    prompt_qos = Qos(reliable, Policy.Durability.Volatile, Policy.History.KeepLast(10), cdr1)
    answer_qos = Qos(reliable, Policy.Durability.TransientLocal, Policy.History.KeepAll, cdr1)

    prompt_topic = Topic(dp, topics["prompt"], String_)
    writer = DataWriter(dp, prompt_topic, qos=prompt_qos)
    readers = {}
    for key, ros_type in ROS_TYPES.items():
        t = Topic(dp, topics[key], raw_type(dds_type(ros_type)))
        readers[key] = DataReader(dp, t, qos=answer_qos)

    def matched():
        return writer.get_publication_matched_status().current_count > 0 and all(
            r.get_subscription_matched_status().current_count > 0 for r in readers.values()
        )

    t0 = time.monotonic()
    while not matched():
        if time.monotonic() > deadline:
            print(json.dumps({"error": "no match with the node's topics", "topics": topics}))
            return 3
        time.sleep(0.02)
    discovery_s = time.monotonic() - t0

    samples = {k: [] for k in readers}
    arrival = {k: [] for k in readers}

    def poll():
        for key, r in readers.items():
            for raw in r.take(N=64):
                if isinstance(raw, bytes):
                    samples[key].append(raw)
                    arrival[key].append(time.monotonic())

    sent = []
    http_ms = []
    ros_ms = []
    latency = req.get("latency", False)
    for p in req["prompts"]:
        n_before = len(samples["objects"])
        sent.append(time.monotonic())
        writer.write(String_(data=p))
        if latency:
            # One prompt at a time: wait for its answer on ~/objects, then the same query over
            # HTTP.
            while len(samples["objects"]) == n_before:
                if time.monotonic() > deadline:
                    print(json.dumps({"error": "timeout waiting for an answer", "prompt": p}))
                    return 4
                poll()
                time.sleep(0.0005)
            ros_ms.append((arrival["objects"][-1] - sent[-1]) * 1e3)
            url = req["http"] + "/query?" + urllib.parse.urlencode({"text": p})
            h0 = time.monotonic()
            with urllib.request.urlopen(url) as resp:
                resp.read()
            http_ms.append((time.monotonic() - h0) * 1e3)
    while any(len(s) < expect for s in samples.values()):
        if time.monotonic() > deadline:
            break
        poll()
        time.sleep(0.005)
    quiet_until = time.monotonic() + 1.0
    while time.monotonic() < quiet_until:
        poll()
        time.sleep(0.02)

    out = {
        "discovery_s": discovery_s,
        "ros_ms": ros_ms,
        "http_ms": http_ms,
    }
    for key, raws in samples.items():
        out[key] = [DECODE[key](store.deserialize_cdr(raw, ROS_TYPES[key])) for raw in raws]
    if req.get("late_subscriber"):
        # A subscription made after the answers were published: transient-local, depth 1, so
        # it receives exactly the last answer.
        late = DataReader(
            dp, Topic(dp, topics["objects"], raw_type(dds_type(ROS_TYPES["objects"]))),
            qos=answer_qos,
        )
        got = []
        until = time.monotonic() + 10
        while time.monotonic() < until and not got:
            got = [x for x in late.take(N=8) if isinstance(x, bytes)]
            time.sleep(0.02)
        time.sleep(0.5)
        got += [x for x in late.take(N=8) if isinstance(x, bytes)]
        out["late_objects"] = [
            decode_objects(store.deserialize_cdr(raw, ROS_TYPES["objects"])) for raw in got
        ]
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
