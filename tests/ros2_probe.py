"""A real rclpy node against ``abh3 run``: run with a ROS 2 venv's Python (tests/test_ros2_real.py).

Prints one JSON object on stdout: what it saw of the graph (nodes, per-topic endpoint names
and GIDs, the node's own endpoints), the topics, /diagnostics, odom at rest, while
driving and (``settle``) once stopped, the service, and the wall-clock times of its cmd_vel publishing (for the frames
the supervisor recorded). Every wait is bounded; a missing thing is reported, not waited
for (a thing that must be absent only for ``absent_wait`` seconds).
"""

from __future__ import annotations

import json
import math
import sys
import time
from typing import Any

import rclpy
from rclpy.node import Node

NODE = "abh3_supervisor"


def main() -> int:
    args = json.loads(sys.argv[1])
    rclpy.init(domain_id=args["domain"])
    node = Node("abh3_probe")
    out: dict[str, Any] = {"errors": []}

    def spin_until(cond: Any, seconds: float) -> bool:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if cond():
                return True
            rclpy.spin_once(node, timeout_sec=0.05)
        return bool(cond())

    try:
        run(node, args, out, spin_until)
    except Exception as exc:  # reported, so the test says what failed
        out["errors"].append(f"{type(exc).__name__}: {exc}")
    print(json.dumps(out), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def run(node: Any, args: dict[str, Any], out: dict[str, Any], spin_until: Any) -> None:
    from diagnostic_msgs.msg import DiagnosticArray  # type: ignore[import-not-found]
    from geometry_msgs.msg import Twist  # type: ignore[import-not-found]
    from nav_msgs.msg import Odometry  # type: ignore[import-not-found]

    wait = float(args.get("wait", 30))
    # what must NOT be there: once the bridge's topics are listed, its command entities
    # would be listed within moments (same participant, same discovery round)
    patience = wait if args["expect_commands"] else float(args.get("absent_wait", 3))

    def in_graph() -> bool:
        return (NODE, "/") in node.get_node_names_and_namespaces()

    out["in_graph"] = spin_until(in_graph, wait)
    out["nodes"] = sorted(f"{ns.rstrip('/')}/{n}" for n, ns in node.get_node_names_and_namespaces())

    want = args["topics"]  # name -> type the docs give
    spin_until(lambda: all(t in dict(node.get_topic_names_and_types()) for t in want), wait)
    out["topics"] = {t: ty for t, ty in node.get_topic_names_and_types() if t in want}
    graph(node, args, out, spin_until)

    diags: list[Any] = []
    odoms: list[Any] = []
    node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    node.create_subscription(Odometry, args["odom"], odoms.append, 10)
    spin_until(lambda: diags and odoms, wait)
    out["diagnostics"] = sorted({(s.name, s.hardware_id) for d in diags for s in d.status})
    if odoms:
        out["odom"] = odometry(odoms[-1])

    service = args["service"]
    spin_until(lambda: service in dict(node.get_service_names_and_types()), patience)
    out["services"] = {s: ty for s, ty in node.get_service_names_and_types() if s == service}
    if args["commands"]:
        call(node, args, out, spin_until)

    cmd = node.create_publisher(Twist, args["cmd_vel"], 10)
    spin_until(lambda: cmd.get_subscription_count() > 0, patience)
    out["cmd_vel_matched"] = cmd.get_subscription_count()
    msg = Twist()
    msg.linear.x, msg.angular.z = args["twist"]
    first = time.time()
    end = time.monotonic() + float(args.get("drive", 2.0))
    while time.monotonic() < end:  # 20 Hz, as a teleop node publishes
        cmd.publish(msg)
        last = time.time()
        rclpy.spin_once(node, timeout_sec=0.05)
    out["cmd_vel"] = {"first": first, "last": last}
    if odoms:  # the latest odom while the twist was still being sent
        out["odom_driving"] = odometry(odoms[-1])
    settle = float(args.get("settle", 0))
    if settle and odoms:  # the robot stopped (silence, then the drives' ramp): where it is
        spin_until(lambda: False, settle)
        out["odom_final"] = odometry(odoms[-1])


def graph(node: Any, args: dict[str, Any], out: dict[str, Any], spin_until: Any) -> None:
    """Per-topic endpoint info (``ros2 topic info -v``) and the node's own endpoints."""

    def infos(topic: str) -> Any:
        if topic in args["subscribed"]:
            return node.get_subscriptions_info_by_topic(topic)
        return node.get_publishers_info_by_topic(topic)

    endpoints: dict[str, list[str]] = {}
    gids: dict[str, list[str]] = {}
    for topic in [*args["published"], *args["subscribed"]]:
        spin_until(lambda t=topic: infos(t), 5)
        found = infos(topic)
        endpoints[topic] = sorted(f"{i.node_namespace.rstrip('/')}/{i.node_name}" for i in found)
        gids[topic] = sorted(bytes(i.endpoint_gid).hex() for i in found)
    out["endpoints"] = endpoints
    out["endpoint_gids"] = gids  # the GIDs rmw made of the discovered endpoints' GUIDs
    if (NODE, "/") in node.get_node_names_and_namespaces():
        # resolved through the node's GIDs in ros_discovery_info: they equal the above
        pubs = node.get_publisher_names_and_types_by_node(NODE, "/")
        subs = node.get_subscriber_names_and_types_by_node(NODE, "/")
        out["node_publishers"] = sorted(t for t, _ in pubs)
        out["node_subscribers"] = sorted(t for t, _ in subs)


def odometry(o: Any) -> dict[str, Any]:
    q = o.pose.pose.orientation
    return {
        "frame_id": o.header.frame_id,
        "child_frame_id": o.child_frame_id,
        "linear_x": o.twist.twist.linear.x,
        "angular_z": o.twist.twist.angular.z,
        "x": o.pose.pose.position.x,
        "y": o.pose.pose.position.y,
        "yaw": 2 * math.atan2(q.z, q.w),
    }


def call(node: Any, args: dict[str, Any], out: dict[str, Any], spin_until: Any) -> None:
    from abh3_can_interface.srv import Abh3Input  # type: ignore[import-not-found]

    client = node.create_client(Abh3Input, args["service"])
    out["service_ready"] = client.wait_for_service(timeout_sec=float(args.get("wait", 30)))
    answers, calls = [], []
    for command in args["commands"]:
        if not out["service_ready"]:
            break
        sent = time.time()
        future = client.call_async(Abh3Input.Request(command=command))
        spin_until(future.done, 10)
        answers.append(future.result().responce if future.done() else None)
        calls.append([sent, time.time()])  # wall clock, as the recording's frames
    out["answers"], out["calls"] = answers, calls


if __name__ == "__main__":
    sys.exit(main())
