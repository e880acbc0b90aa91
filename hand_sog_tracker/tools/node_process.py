"""The tracker node as a child process, and DDS confined to this machine.

:func:`loopback_dds` forces Fast DDS with the package's loopback-only profile and
a ROS domain for the ``rclpy.init`` calls made inside it; :class:`NodeProcess`
runs ``python -m hand_sog_tracker.ros.node`` with ``ROS_HOME`` in a scratch
directory.  :class:`~hand_sog_tracker.tools.node_harness.NodeHarness` puts both
together.
"""

from __future__ import annotations

import contextlib
import importlib.resources
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Iterator, Mapping, Sequence, Union

from hand_sog_tracker.errors import HandSogError, InputError

__all__ = ["NodeProcess", "loopback_dds", "ros_param_args", "Value"]

#: A node parameter value.
Value = Union[bool, int, float, str]


#: Environment variables :func:`loopback_dds` sets (and restores afterwards).
_DDS_ENV = (
    "FASTRTPS_DEFAULT_PROFILES_FILE",
    "FASTDDS_DEFAULT_PROFILES_FILE",
    "ROS_DOMAIN_ID",
    "RMW_IMPLEMENTATION",
    "ROS_LOCALHOST_ONLY",
    "ROS_AUTOMATIC_DISCOVERY_RANGE",
    "ROS_STATIC_PEERS",
)


@contextlib.contextmanager
def loopback_dds(domain_id: int) -> Iterator[Path]:
    """Confine DDS to this machine for ``rclpy.init`` calls made inside the block.

    Forces Fast DDS (``RMW_IMPLEMENTATION=rmw_fastrtps_cpp``) with the
    package's loopback-only profile ``hand_sog_tracker/data/fastdds_loopback.xml``
    and ``ROS_DOMAIN_ID=domain_id``; the previous environment is restored on exit.

    Yields
    ------
    Path
        The profile file in use.

    Raises
    ------
    HandSogError
        If the profile is not installed with the package.
    """
    if not 0 <= int(domain_id) <= 232:
        raise InputError(f"ROS domain id must be in [0, 232], got {domain_id}")
    resource = importlib.resources.files("hand_sog_tracker") / "data" / "fastdds_loopback.xml"
    with importlib.resources.as_file(resource) as profile:
        if not Path(profile).is_file():
            raise HandSogError(f"the loopback Fast DDS profile is missing from the package ({profile})")
        saved = {k: os.environ.get(k) for k in _DDS_ENV}
        try:
            for k in ("ROS_LOCALHOST_ONLY", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_STATIC_PEERS"):
                os.environ.pop(k, None)
            os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(profile)
            os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] = str(profile)
            os.environ["ROS_DOMAIN_ID"] = str(int(domain_id))
            os.environ["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
            yield Path(profile)
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v


def ros_param_args(params: Mapping[str, Value]) -> list[str]:
    """``--ros-args`` items ``-p name:=value`` for ``params`` (typed as YAML reads them back)."""
    out: list[str] = []
    for name, value in params.items():
        if isinstance(value, bool):
            text = "true" if value else "false"
        elif isinstance(value, float):
            text = repr(float(value))
        elif isinstance(value, int):
            text = str(value)
        else:
            text = "'" + str(value).replace("'", "''") + "'"
        out += ["-p", f"{name}:={text}"]
    return out


class NodeProcess:
    """The tracker node (``python -m hand_sog_tracker.ros.node``) as a child process.

    Its output goes to ``workdir/tracker_node.log``; :meth:`stop` ends it
    (SIGINT, then SIGTERM, then SIGKILL) and is safe to call twice.

    Parameters
    ----------
    workdir : Path
        Scratch directory: ``ROS_HOME`` of the node and its log.
    ros_args : sequence of str
        Items after ``--ros-args`` (``-p name:=value``, ``--params-file F``, ``-r a:=b``).
    """

    def __init__(self, workdir: Path, ros_args: Sequence[str] = ()) -> None:
        import hand_sog_tracker

        self.log_path = workdir / "tracker_node.log"
        env = dict(os.environ)
        root = str(Path(hand_sog_tracker.__file__).resolve().parents[1])
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
        env["ROS_HOME"] = str(workdir)  # logs and the (absent) user model stay in the scratch dir
        self.cmd = [sys.executable, "-m", "hand_sog_tracker.ros.node", "--ros-args", *ros_args]
        self._log = open(self.log_path, "wb")  # closed in stop()
        try:
            self.proc = subprocess.Popen(self.cmd, env=env, stdout=self._log, stderr=subprocess.STDOUT)
        except OSError as err:
            self._log.close()
            raise HandSogError(f"cannot start the tracker node: {err}") from err

    def alive(self) -> bool:
        """True while the node runs."""
        return self.proc.poll() is None

    def log_tail(self, n: int = 15) -> str:
        """Last lines of the node's output."""
        try:
            lines = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(lines[-n:])

    def stop(self) -> int | None:
        """End the node; its exit code."""
        for sig, wait_s in ((signal.SIGINT, 10.0), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            if self.proc.poll() is not None:
                break
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=wait_s)
            except subprocess.TimeoutExpired:
                continue
        if not self._log.closed:
            self._log.close()
        return self.proc.poll()
