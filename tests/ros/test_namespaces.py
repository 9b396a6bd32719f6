"""Namespaces and ``--ros-args``: the graph moves as a whole with ``-r __ns:=/cellX``.

Default topic names are relative (``camera/image_raw``, ``armourcam/poses``, ``hall/run_id``), so
a node pushed into a namespace uses it for every topic but ``/diagnostics``; the status names
carry the node's fully qualified name; ``armourcam graph``, ``replay`` and ``record`` hand
everything after ``--ros-args`` to rclpy (graph: to every node).
"""

from __future__ import annotations

import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosutil import Nodes, Probe, Recorder, armourcam, start_armourcam

from armourcam import bagio, graph, image_codec
from armourcam.cli import build_parser
from armourcam.graph import latched_qos, stream_qos
from pose_estimator.camera import CameraModel

#: Graph-wide names every node may use outside its namespace.
GLOBAL = {"/diagnostics", "/rosout", "/parameter_events"}


def _endpoints(probe: Probe, name: str, ns: str) -> set[str]:
    """Topics node ``ns/name`` publishes or subscribes (as the graph shows them)."""
    n = probe.node
    pubs = n.get_publisher_names_and_types_by_node(name, ns)
    subs = n.get_subscriber_names_and_types_by_node(name, ns)
    return {t for t, _ in pubs} | {t for t, _ in subs}


def _wait_nodes(probe: Probe, ns: str, names: tuple[str, ...], timeout: float = 30.0) -> bool:
    def there() -> bool:
        return all((n, ns) in probe.node.get_node_names_and_namespaces() for n in names)

    return probe.spin_until(there, timeout)


def test_nodes_in_a_namespace_use_it_for_every_topic_and_status_name(
    nodes: Nodes, probe: Probe, tmp_path: Path
) -> None:
    from diagnostic_msgs.msg import DiagnosticArray

    ns = "/cell_ns1"
    names: list[str] = []
    probe.node.create_subscription(
        DiagnosticArray, "/diagnostics", lambda m: names.extend(s.name for s in m.status), 50
    )
    nodes.start("fiducial_detector", "-r", f"__ns:={ns}")
    nodes.start("pose_estimator", "-r", f"__ns:={ns}")
    nodes.start(
        "displacement_matcher", "-r", f"__ns:={ns}", params={"data_dir": str(tmp_path / "data")}
    )
    assert _wait_nodes(probe, ns, graph.NODE_NAMES), probe.node.get_node_names_and_namespaces()
    want = {
        "fiducial_detector": {"camera/image_raw", "armourcam/detections"},
        "pose_estimator": {
            "armourcam/detections",
            "camera/camera_info",
            "armourcam/poses",
            "armourcam/pose_array",
        },
        "displacement_matcher": {
            "armourcam/poses",
            "hall/run_active",
            "hall/run_id",
            "armourcam/capture_baseline",
            "armourcam/markers",
            "armourcam/displacements",
            "armourcam/report",
            "armourcam/baseline",
        },
    }
    seen: dict[str, set[str]] = {}
    # Every node also publishes the aggregator's /diagnostics, not the cell's (waited for with
    # the rest: discovery reports a node's endpoints one by one).
    diagnostics: dict[str, bool] = {}

    def complete() -> bool:
        for name in want:
            found = _endpoints(probe, name, ns)
            seen[name] = found - GLOBAL
            diagnostics[name] = "/diagnostics" in found
        return all(seen[n] >= {f"{ns}/{t}" for t in want[n]} for n in want) and all(
            diagnostics.values()
        )

    assert probe.spin_until(complete, 20.0), (seen, diagnostics)
    # Nothing outside the namespace but the graph-wide names.
    assert all(t.startswith(f"{ns}/") for n in want for t in seen[n]), seen
    statuses = {f"{ns}/{n}: armourcam" for n in graph.NODE_NAMES}
    assert probe.spin_until(lambda: statuses <= set(names), 20.0), set(names)


def test_compressed_input_follows_the_namespace_and_a_relative_remap(
    nodes: Nodes, probe: Probe
) -> None:
    """``<image_topic>/compressed`` is derived from the resolved (namespaced, remapped) name, and
    frames sent there come out on the namespaced detections topic."""
    from sensor_msgs.msg import CompressedImage, PointCloud2

    ns = "/cell_ns2"
    nodes.start(
        "fiducial_detector",
        "-r",
        f"__ns:={ns}",
        "-r",
        "camera/image_raw:=cam2/image_raw",
        params={"transport": "compressed"},
    )
    qos = stream_qos("reliable", 10)
    pub = probe.node.create_publisher(CompressedImage, f"{ns}/cam2/image_raw/compressed", qos)
    out: list[Any] = []
    probe.node.create_subscription(PointCloud2, f"{ns}/armourcam/detections", out.append, qos)
    assert probe.spin_until(lambda: pub.get_subscription_count() > 0, 30.0), nodes.log(
        "fiducial_detector"
    )
    assert _wait_nodes(probe, ns, ("fiducial_detector",))
    assert _endpoints(probe, "fiducial_detector", ns) - GLOBAL == {
        f"{ns}/cam2/image_raw/compressed",
        f"{ns}/armourcam/detections",
    }
    probe.spin_for(1.0)
    img = np.full((120, 160), 128, np.uint8)
    msg = CompressedImage(**image_codec.compressed_to_msg_fields(img, "png"))
    pub.publish(msg)
    assert probe.spin_until(lambda: len(out) == 1, 20.0), nodes.log("fiducial_detector")


@pytest.mark.parametrize("mode", [[], ["--one-process"]], ids=["processes", "one-process"])
def test_graph_hands_ros_args_to_every_node(probe: Probe, tmp_path: Path, mode: list[str]) -> None:
    from rclpy.parameter import parameter_value_to_python as value

    ns = "/cell_ns3"
    data = tmp_path / "data"
    launcher = start_armourcam(
        "graph",
        *mode,
        "--log-dir",
        str(tmp_path),
        "--ros-args",
        "-r",
        f"__ns:={ns}",
        "-p",
        "diameter_mm:=10.0",
        "-p",
        f"data_dir:={data}",
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        found = _wait_nodes(probe, ns, graph.NODE_NAMES)
        assert found, (launcher.poll(), probe.node.get_node_names_and_namespaces())
        assert value(probe.get_parameter(f"{ns}/pose_estimator", "diameter_mm")) == 10.0
        assert value(probe.get_parameter(f"{ns}/displacement_matcher", "data_dir")) == str(data)
    finally:
        # More time than the launcher gives its nodes (5 s), so that a slow node shows in err.
        graph.stop_processes([launcher], timeout=15.0)
        _, err = launcher.communicate(timeout=10.0)
    assert launcher.returncode in (0, -2, 130), err  # stopped by the SIGINT, not failed


def test_ros_args_end_the_commands_own_arguments() -> None:
    parser = build_parser()
    ros = ["-r", "__ns:=/cell2", "-p", "diameter_mm:=10.0"]
    args = parser.parse_args(["graph", "--one-process", "--ros-args", *ros])
    assert args.one_process and args.ros_args == ros
    args = parser.parse_args(["replay", "bag", "--topics", "/a", "/b", "--ros-args", *ros])
    assert args.topics == ["/a", "/b"] and args.ros_args == ros
    args = parser.parse_args(["record", "--out", "x", "/a", "--ros-args", *ros])
    assert args.topics == ["/a"] and args.ros_args == ros
    assert parser.parse_args(["record", "--out", "x"]).ros_args == []


def test_replay_publishes_bag_names_relative_to_its_namespace() -> None:
    from armourcam.graph import replay_name

    assert replay_name("/camera/image_raw", {}) == "camera/image_raw"
    assert replay_name("/cell2/hall/run_id", {}) == "cell2/hall/run_id"
    assert replay_name("/diagnostics", {}) == "/diagnostics"  # graph-wide, never moved
    remap = {"/raspicam/image": "/camera/image_raw", "/a": "b", "/skip": ""}
    assert [replay_name(t, remap) for t in remap] == ["/camera/image_raw", "b", ""]


def _bag(path: Path, n: int) -> None:
    """``n`` small frames with camera info and a hall run id, recorded under root names."""
    cam = CameraModel.ideal(160, 120, 200.0)
    with bagio.BagWriter(path) as w:
        w.write_string("/hall/run_id", "wave-1", 1_700_000_000 * 10**9)
        for k in range(n):
            t = 1_700_000_000 * 10**9 + (k + 1) * 100_000_000
            w.write_camera_info("/camera/camera_info", cam, t)
            w.write_image("/camera/image_raw", np.full((120, 160), 120, np.uint8), t + 1)


def test_replay_into_a_namespace_feeds_a_namespaced_graph(
    nodes: Nodes, probe: Probe, tmp_path: Path
) -> None:
    """``replay --ros-args -r __ns:=/cellX`` publishes the bag's root names under the namespace:
    the namespaced detector confirms every frame (as fast as consumed: its namespaced output is
    watched), and the hall's run id arrives on ``/cellX/hall/run_id``."""
    from std_msgs.msg import String

    ns = "/cell_ns4"
    bag = tmp_path / "bag"
    _bag(bag, 5)
    nodes.start("fiducial_detector", "-r", f"__ns:={ns}")
    nodes.start("pose_estimator", "-r", f"__ns:={ns}")
    run_ids: list[str] = []
    probe.node.create_subscription(
        String, f"{ns}/hall/run_id", lambda m: run_ids.append(m.data), latched_qos(10)
    )
    assert _wait_nodes(probe, ns, ("fiducial_detector", "pose_estimator"))
    out = armourcam(
        "replay",
        str(bag),
        "--as-fast-as-consumed",
        "--wait-for",
        "armourcam/detections",  # relative: the pose estimator in the namespace
        "--wait-for",
        "hall/run_id",  # this probe: its latched event must reach it before the replay exits
        "--ros-args",
        "-r",
        f"__ns:={ns}",
    )
    assert out.returncode == 0, out.stderr + nodes.log("fiducial_detector")
    assert "no subscriber yet" not in out.stderr, out.stderr
    assert f"{ns}/camera/image_raw: 5" in out.stdout, out.stdout
    assert f"{ns}/camera/camera_info: 5" in out.stdout, out.stdout
    assert "confirmed by the detector: 5" in out.stdout, out.stdout
    assert probe.spin_until(lambda: run_ids == ["wave-1"], 10.0), run_ids


def test_record_in_a_namespace_records_the_cells_topics(
    probe: Probe, tmp_path: Path, recorder: Callable[..., Recorder]
) -> None:
    """``record --ros-args -r __ns:=/cellX`` records the cell's outputs (default list) under
    their full names, and ``/diagnostics`` as it is."""
    from std_msgs.msg import String

    ns = "/cell_ns5"
    report = probe.node.create_publisher(String, f"{ns}/armourcam/report", latched_qos())
    root = probe.node.create_publisher(String, "/armourcam/report", latched_qos())
    report.publish(String(data='{"run": 1}'))
    root.publish(String(data='{"run": "other cell"}'))
    bag = tmp_path / "bag"
    rec = recorder(bag, "--duration", "4", "--ros-args", "-r", f"__ns:={ns}")
    probe.spin_until(lambda: rec.proc.poll() is not None, 60.0)
    rec.proc.wait(10.0)  # ends by itself (--duration)
    stdout = rec.stop()
    assert rec.proc.returncode == 0, "".join(rec.lines)
    assert f"{ns}/armourcam/report: 1" in stdout, stdout
    with bagio.open_bag(bag) as b:
        assert set(b.topics) == {f"{ns}/armourcam/report"}
        (msg,) = b.messages([f"{ns}/armourcam/report"])
        assert msg.message.data == '{"run": 1}'


CONFIG = Path(__file__).resolve().parents[2] / "config" / "armourcam.params.yaml"


@pytest.mark.parametrize("ns", ["/", "/cell_ns6"])
def test_shipped_params_file_applies_in_any_namespace(ns: str) -> None:
    """``config/armourcam.params.yaml`` reaches every node whatever its namespace (a section
    keyed by the bare node name would match only in ``/``, silently), and names the nodes'
    relative default topics, so ``--params`` does not pin a namespaced graph to ``/``."""
    import importlib

    import rclpy

    context = rclpy.Context()
    rclpy.init(
        context=context, args=["x", "--ros-args", "-r", f"__ns:={ns}", "--params-file", str(CONFIG)]
    )
    try:
        for name in graph.NODE_NAMES:
            params = importlib.import_module(f"{name}.node").PARAMS
            node = rclpy.create_node(
                name, context=context, automatically_declare_parameters_from_overrides=True
            )
            try:
                topics = [p for p in params if p.name.endswith("_topic")]
                missing = [p.name for p in topics if not node.has_parameter(p.name)]
                assert not missing, (name, missing)  # the section did not match
                for p in topics:
                    assert node.get_parameter(p.name).value == p.default, (name, p.name)
            finally:
                node.destroy_node()
    finally:
        context.try_shutdown()
