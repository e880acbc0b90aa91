"""A reusable harness: ``tracker_node`` as a child process on loopback DDS, driven from here.

One job: drive a running node (start, publish, collect, stop); kept together because the
process, its DDS participant and the collected outputs share one lifetime.

Used by ``evaluate_bag --through-node`` (:mod:`hand_sog_tracker.tools.node_eval`),
node tests and demos::

    from hand_sog_tracker.tools.node_harness import NodeHarness

    with NodeHarness(domain_id=82, params={"handedness": "left"}) as node:
        node.publish_depth(depth_mm, intrinsics, stamp_ns)        # CameraInfo + Image
        node.wait_for(lambda out: stamp_ns in out.markers, timeout_s=5.0)
        tips_mm = node.outputs.markers[stamp_ns].fingertips_mm   # (5, 3) or None

On entry the harness confines DDS to this machine (:func:`loopback_dds`: Fast
DDS with the package's loopback-only profile, ``ROS_DOMAIN_ID=domain_id``),
starts ``python -m hand_sog_tracker.ros.node`` with ``ROS_HOME`` in a scratch
directory (so the user's ``~/.ros`` hand model and logs are never touched),
creates its own rclpy context with a helper node that publishes the node's
inputs and listens to ``hand/fingertips`` (MarkerArray), ``hand/joint_states``
and ``/diagnostics``, spins it on a thread, and waits until the node is
connected.  :meth:`NodeHarness.stop` (also on exit) ends both and restores the
environment.

(A little over 400 lines: one class with its output types and the message
conversions it needs; the process and DDS parts are in
:mod:`hand_sog_tracker.tools.node_process`.)
"""

from __future__ import annotations

import contextlib
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import HandSogError, InputError
from hand_sog_tracker.interface import (
    DEPTH_TOPIC,
    DIAG_COUNTER_KEYS,
    DIAGNOSTICS_TOPIC,
    FINGERTIPS_NS,
    FINGERTIPS_TOPIC,
    INFO_TOPIC,
    JOINTS_TOPIC,
    NODE_NAME,
    stamp_to_ns,
)
from hand_sog_tracker.tools.node_process import NodeProcess, Value, loopback_dds, ros_param_args

__all__ = [
    "DEPTH_TOPIC",
    "INFO_TOPIC",
    "NodeHarness",
    "NodeOutputs",
    "MarkerOutput",
    "NodeProcess",
    "loopback_dds",
    "markers_to_output",
    "diagnostic_counters",
    "ros_param_args",
]

# Topics (relative to the node's namespace, except /diagnostics): hand_sog_tracker.interface.
MARKERS_TOPIC = FINGERTIPS_TOPIC
DIAG_TOPIC = DIAGNOSTICS_TOPIC


@dataclass(frozen=True, eq=False)
class MarkerOutput:
    """One ``hand/fingertips`` MarkerArray received.

    Attributes
    ----------
    t : float
        ``time.monotonic()`` at reception.
    fingertips_mm : array, shape (5, 3) or None
        Fingertip markers (thumb .. little), mm; None for a DELETEALL (hand lost).
    """

    t: float
    fingertips_mm: NDArray[np.float64] | None


def markers_to_output(msg: Any) -> tuple[int, NDArray[np.float64] | None] | None:
    """(stamp ns, fingertips (5, 3) mm or None for DELETEALL) of a MarkerArray; None if empty."""
    if not msg.markers:
        return None
    stamp_ns = stamp_to_ns(msg.markers[0].header.stamp)
    tips = np.full((5, 3), np.nan)
    for m in msg.markers:
        if m.ns == FINGERTIPS_NS and m.action == 0 and 0 <= m.id < 5:  # ADD
            p = m.pose.position
            tips[m.id] = (p.x * 1000.0, p.y * 1000.0, p.z * 1000.0)
    return stamp_ns, (tips if np.all(np.isfinite(tips)) else None)


_NODE_COUNTERS = tuple(k for k in DIAG_COUNTER_KEYS if k != "frames_missed")
#: Keys of the counters dicts of :func:`diagnostic_counters`.
COUNTER_KEYS = ("received", "processed", "dropped", "rejected")


def diagnostic_counters(msg: Any, node: str | None = None) -> dict[str, Any] | None:
    """Frame counters (``received``, ``processed``, ``dropped``, ``rejected``, ``last_problem``)
    of the tracker node's status in a DiagnosticArray, or None.

    ``node``: only the status of the node with this fully qualified name
    (e.g. ``/ns/hand_sog_tracker``); default: any tracker node.
    """
    for status in msg.status:
        if status.name.startswith(NODE_NAME) and (node is None or status.name.endswith(f": {node}")):
            values = {kv.key: kv.value for kv in status.values}
            out: dict[str, Any] = {}
            for key in _NODE_COUNTERS:
                try:
                    out[key.removeprefix("frames_")] = int(values[key])
                except (KeyError, ValueError):
                    return None
            out["last_problem"] = values.get("last_problem", "")
            return out
    return None


@dataclass
class NodeOutputs:
    """What the harness received from the node (a snapshot; see :attr:`NodeHarness.outputs`).

    Attributes
    ----------
    markers : dict
        Header stamp (ns) of the depth image -> :class:`MarkerOutput` (the first one).
    joint_states : dict
        Header stamp (ns) -> (reception ``time.monotonic()``, joint angles (20,) rad).
    diagnostics : list
        (reception time, counters of :func:`diagnostic_counters`), in arrival order.
    last_activity : float
        ``time.monotonic()`` of the last marker received (or of the start).
    hand_markers : dict
        With ``max_hands`` 2: ``left`` / ``right`` -> stamp (ns) -> :class:`MarkerOutput` of
        ``hand/<side>/fingertips`` (the first one).
    """

    markers: dict[int, MarkerOutput] = field(default_factory=dict)
    joint_states: dict[int, tuple[float, NDArray[np.float64]]] = field(default_factory=dict)
    diagnostics: list[tuple[float, dict[str, Any]]] = field(default_factory=list)
    last_activity: float = field(default_factory=time.monotonic)
    hand_markers: dict[str, dict[int, MarkerOutput]] = field(default_factory=dict)

    def copy(self) -> "NodeOutputs":
        """A shallow copy (new containers)."""
        return NodeOutputs(
            dict(self.markers), dict(self.joint_states), list(self.diagnostics), self.last_activity,
            {s: dict(m) for s, m in self.hand_markers.items()},
        )


class NodeHarness:
    """``tracker_node`` in a child process on loopback DDS; publish its inputs, collect its outputs.

    Use as a context manager (or call :meth:`start` / :meth:`stop`).

    Parameters
    ----------
    domain_id : int
        ROS domain of the node and the harness (0-232); loopback DDS only.
    params : mapping, optional
        Node parameters, passed as ``-p name:=value`` (e.g. ``{"handedness": "left"}``).
    params_file : str or Path, optional
        A ROS 2 params YAML passed as ``--params-file`` (``params`` win over it).
    workdir : str or Path, optional
        Directory for the node's ``ROS_HOME`` and log (``tracker_node.log``);
        default: a temporary directory removed by :meth:`stop`.
    namespace : str
        Namespace of the node (``/ns``); the harness uses the same topics in it.
        Give each harness its own namespace when several may run in one domain
        at once (``/diagnostics`` is shared but filtered by the node's name).
    connect_timeout_s : float
        How long :meth:`start` waits for the node to subscribe and advertise.
    ros_args : sequence of str
        More ``--ros-args`` items for the node.

    Notes
    -----
    Unless ``params`` or ``params_file`` sets it, ``user_model_path`` points to a
    file that does not exist, so the node starts with the default hand model.
    """

    def __init__(
        self,
        domain_id: int,
        params: Mapping[str, Value] | None = None,
        params_file: str | Path | None = None,
        workdir: str | Path | None = None,
        namespace: str = "",
        connect_timeout_s: float = 30.0,
        ros_args: Sequence[str] = (),
    ) -> None:
        if not 0 <= int(domain_id) <= 232:
            raise InputError(f"ROS domain id must be in [0, 232], got {domain_id}")
        if namespace and not namespace.startswith("/"):
            raise InputError(f"namespace must start with '/', got {namespace!r}")
        self.domain_id = int(domain_id)
        self.params = dict(params or {})
        self.params_file = None if params_file is None else Path(params_file)
        self.namespace = namespace.rstrip("/")
        #: Fully qualified name of the node (its /diagnostics status is told apart by it).
        self.node_fqn = f"{self.namespace}/{NODE_NAME}"
        self.connect_timeout_s = float(connect_timeout_s)
        self._workdir_arg = None if workdir is None else Path(workdir)
        self._extra_args = list(ros_args)
        self._stack: contextlib.ExitStack | None = None
        self._lock = threading.Lock()
        self._outputs = NodeOutputs()
        self.process: NodeProcess | None = None
        self.workdir: Path | None = None
        #: The harness's own rclpy node (create more publishers/subscriptions on it).
        self.node: Any = None
        self.context: Any = None
        self._pubs: dict[str, Any] = {}
        self._spin_thread: threading.Thread | None = None
        self._executor: Any = None

    # -- life cycle ------------------------------------------------------------
    def __enter__(self) -> "NodeHarness":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def topic(self, name: str) -> str:
        """Full name of the node's topic ``name`` (relative names get the namespace)."""
        return name if name.startswith("/") else f"{self.namespace}/{name}"

    def node_ros_args(self) -> list[str]:
        """The ``--ros-args`` items the node is started with."""
        args: list[str] = []
        if self.namespace:
            args += ["-r", f"__ns:={self.namespace}"]
        if self.params_file is not None:
            args += ["--params-file", str(self.params_file)]
        params = dict(self.params)
        if "user_model_path" not in params and self.params_file is None:
            assert self.workdir is not None
            params["user_model_path"] = str(self.workdir / "no_user_model.yaml")
        return args + ros_param_args(params) + self._extra_args

    def start(self) -> "NodeHarness":
        """Start the node and the harness's rclpy node; wait until they are connected.

        Raises
        ------
        HandSogError
            The node cannot be started, exits early or does not connect within
            ``connect_timeout_s`` (the message holds the end of its log).
        """
        if self._stack is not None:
            return self
        if self.params_file is not None and not self.params_file.is_file():
            raise InputError(f"params file not found: {self.params_file}")
        stack = contextlib.ExitStack()
        self._stack = stack
        try:
            stack.enter_context(loopback_dds(self.domain_id))
            if self._workdir_arg is None:
                self.workdir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="node_harness_")))
            else:
                self.workdir = self._workdir_arg
                self.workdir.mkdir(parents=True, exist_ok=True)
            self.process = NodeProcess(self.workdir, self.node_ros_args())
            stack.callback(self.process.stop)
            self._start_ros(stack)
            self._wait_connected()
        except BaseException:
            self.stop()
            raise
        return self

    def _start_ros(self, stack: contextlib.ExitStack) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image, JointState
        from visualization_msgs.msg import MarkerArray

        ctx = Context()
        rclpy.init(context=ctx)
        self.context = ctx
        stack.callback(rclpy.try_shutdown, context=ctx)
        node = rclpy.create_node("node_harness", context=ctx, start_parameter_services=False)
        self.node = node
        stack.callback(node.destroy_node)
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        inputs = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self._pubs = {
            "depth": node.create_publisher(Image, self.topic(DEPTH_TOPIC), inputs),
            "info": node.create_publisher(CameraInfo, self.topic(INFO_TOPIC), inputs),
        }
        node.create_subscription(MarkerArray, self.topic(MARKERS_TOPIC), self._on_markers, reliable)
        node.create_subscription(JointState, self.topic(JOINTS_TOPIC), self._on_joints, reliable)
        node.create_subscription(DiagnosticArray, DIAG_TOPIC, self._on_diagnostics, reliable)
        if int(self.params.get("max_hands", 1)) > 1:  # (the per-hand fingertips, hand_topics.py)
            from hand_sog_tracker.ros.hand_topics import per_hand_topic

            for side in ("left", "right"):
                self._outputs.hand_markers[side] = {}
                node.create_subscription(
                    MarkerArray, self.topic(per_hand_topic(side, "fingertips")),
                    lambda msg, s=side: self._on_hand_markers(s, msg), reliable,
                )
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        self._executor = executor

        def spin() -> None:
            while ctx.ok():
                try:
                    executor.spin_once(timeout_sec=0.05)
                except Exception:  # noqa: BLE001 - context shut down while spinning
                    return

        self._spin_thread = threading.Thread(target=spin, name="node_harness_spin", daemon=True)
        self._spin_thread.start()

        def join() -> None:
            executor.shutdown(timeout_sec=5.0)
            rclpy.try_shutdown(context=ctx)
            if self._spin_thread is not None:
                self._spin_thread.join(timeout=5.0)

        stack.callback(join)

    def _wait_connected(self) -> None:
        assert self.process is not None
        deadline = time.monotonic() + self.connect_timeout_s
        while not (
            all(p.get_subscription_count() > 0 for p in self._pubs.values())
            and self.node.count_publishers(self.topic(MARKERS_TOPIC)) > 0
        ):
            self.check_alive("before connecting")
            if time.monotonic() > deadline:
                raise HandSogError(
                    f"the tracker node did not connect within {self.connect_timeout_s:.0f} s "
                    f"(ROS_DOMAIN_ID {self.domain_id}, loopback DDS); its output:\n{self.process.log_tail()}"
                )
            time.sleep(0.05)

    def stop(self) -> int | None:
        """Stop the harness and the node (idempotent); the node's exit code (None if never started)."""
        stack, self._stack = self._stack, None
        if stack is not None:
            stack.close()
        return None if self.process is None else self.process.proc.poll()

    def alive(self) -> bool:
        """True while the node process runs."""
        return self.process is not None and self.process.alive()

    def check_alive(self, when: str = "") -> None:
        """Raise HandSogError (with the end of the node's log) if the node has exited."""
        if self.process is not None and not self.process.alive():
            raise HandSogError(
                f"the tracker node exited with code {self.process.proc.returncode}"
                f"{' ' + when if when else ''}:\n{self.process.log_tail()}"
            )

    def log_tail(self, n: int = 15) -> str:
        """Last lines of the node's output."""
        return "" if self.process is None else self.process.log_tail(n)

    # -- inputs ----------------------------------------------------------------
    def publish(self, which: str, payload: Any) -> None:
        """Publish on the node's ``"depth"`` or ``"info"`` input: an rclpy message or CDR bytes."""
        try:
            pub = self._pubs[which]
        except KeyError:
            raise InputError(f"unknown input {which!r}; use 'depth' or 'info'") from None
        pub.publish(payload)

    def publish_depth(
        self,
        depth_mm: NDArray,
        intrinsics: Intrinsics,
        stamp_ns: int,
        encoding: str = "16UC1",
        with_info: bool = True,
    ) -> None:
        """Publish a depth image (and, by default, its CameraInfo first), same stamp.

        Parameters
        ----------
        depth_mm : array, shape (H, W)
            Depth, mm (0/NaN = invalid).
        intrinsics : Intrinsics
        stamp_ns : int
            Header stamp, ns (the outputs are keyed by it).
        encoding : {"16UC1", "32FC1"}
        """
        from hand_sog_tracker.tools.bagio import camera_info_msg, depth_image_msg, typestore

        ts = typestore()
        if with_info:
            info = camera_info_msg(intrinsics, stamp_ns)
            self.publish("info", ts.serialize_cdr(info, info.__msgtype__).tobytes())
        img = depth_image_msg(depth_mm, stamp_ns, encoding=encoding)  # type: ignore[arg-type]
        self.publish("depth", ts.serialize_cdr(img, img.__msgtype__).tobytes())

    # -- outputs ---------------------------------------------------------------
    def _on_markers(self, msg: Any) -> None:
        t = time.monotonic()
        out = markers_to_output(msg)
        if out is None:
            return
        with self._lock:
            self._outputs.markers.setdefault(out[0], MarkerOutput(t, out[1]))
            self._outputs.last_activity = t

    def _on_hand_markers(self, side: str, msg: Any) -> None:
        t = time.monotonic()
        out = markers_to_output(msg)
        if out is None:
            return
        with self._lock:
            self._outputs.hand_markers[side].setdefault(out[0], MarkerOutput(t, out[1]))
            self._outputs.last_activity = t

    def _on_joints(self, msg: Any) -> None:
        t = time.monotonic()
        stamp = stamp_to_ns(msg.header.stamp)
        with self._lock:
            self._outputs.joint_states.setdefault(stamp, (t, np.asarray(msg.position, dtype=np.float64)))

    def _on_diagnostics(self, msg: Any) -> None:
        counters = diagnostic_counters(msg, self.node_fqn)
        if counters is not None:
            with self._lock:
                self._outputs.diagnostics.append((time.monotonic(), counters))

    @property
    def outputs(self) -> NodeOutputs:
        """A snapshot of everything received so far."""
        with self._lock:
            return self._outputs.copy()

    def clear_outputs(self) -> None:
        """Forget the markers and joint states received so far (diagnostics are kept)."""
        with self._lock:
            self._outputs.markers.clear()
            self._outputs.joint_states.clear()
            for m in self._outputs.hand_markers.values():
                m.clear()

    def note_activity(self, t: float) -> None:
        """Move :attr:`NodeOutputs.last_activity` to at least ``t``."""
        with self._lock:
            self._outputs.last_activity = max(self._outputs.last_activity, t)

    def wait_for(self, predicate: Callable[[NodeOutputs], bool], timeout_s: float, poll_s: float = 0.01) -> bool:
        """Wait until ``predicate(outputs)`` holds; False on timeout.

        Raises
        ------
        HandSogError
            If the node exits while waiting.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            if predicate(self.outputs):
                return True
            self.check_alive("while waiting for its outputs")
            if time.monotonic() >= deadline:
                return False
            time.sleep(poll_s)
