"""``calibrate_hand``: ask a running tracker node to fit the hand model to the current frames.

Hold an open, flat hand with relaxed fingers toward the camera for about a second
while the tracker follows it, then run::

    calibrate_hand [--timeout 10] [--node-name hand_sog_tracker]

Prints the service's answer (fitted scale factors, the fit score before and
after, the guard's held-out scores of the current and the fitted model, where
the model was saved) and exits 0 on success, 1 otherwise (including a fit the
guard refused: then nothing was changed or saved).  The node keeps tracking
while it fits.  With ``max_hands: 2`` the answer has one part per hand
(``left hand: ... | right hand: ...``) and success means at least one hand's fit
was accepted and saved (to that hand's file).
"""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.utilities import remove_ros_args
from std_srvs.srv import Trigger

__all__ = ["service_name", "main"]

#: Seconds added to ``--timeout`` while waiting for the answer (a fit takes 1-8 s, more on a busy machine).
CALL_MARGIN_S = 30.0


def service_name(node_name: str) -> str:
    """Calibration service of a node: ``hand_sog_tracker`` -> ``/hand_sog_tracker/calibrate``.

    A name with namespace (``/robot/hand_sog_tracker``) is kept as given.
    """
    name = node_name.strip().rstrip("/")
    if not name:
        raise ValueError("node name must not be empty")
    return (name if name.startswith("/") else "/" + name) + "/calibrate"


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``calibrate_hand`` (also read by the documentation)."""
    parser = argparse.ArgumentParser(
        prog="calibrate_hand",
        description="Calibrate the hand model of a running hand_sog_tracker node: hold an open "
        "hand with relaxed fingers toward the camera for a second, then run this. The fitted model "
        "is used and saved only if it explains frames it was not fitted on better (exit 1 otherwise).",
    )
    parser.add_argument(
        "--timeout", type=float, default=10.0, metavar="S",
        help="seconds to wait for the service to appear (default 10); the answer may take "
        f"{CALL_MARGIN_S:.0f} s longer",
    )
    parser.add_argument(
        "--node-name", default="hand_sog_tracker",
        help="name (with namespace if any) of the tracker node (default hand_sog_tracker)",
    )
    return parser


def _parse(argv: Sequence[str]) -> argparse.Namespace:
    parser = build_parser()
    ns = parser.parse_args(list(argv))
    if not ns.timeout > 0:
        parser.error("--timeout must be positive")
    return ns


def main(args: list[str] | None = None) -> int:
    """Call the service and print its answer; returns the exit code (0 success, 1 failure)."""
    argv = sys.argv if args is None else args
    opts = _parse(remove_ros_args(args=argv)[1:])
    name = service_name(opts.node_name)
    rclpy.init(args=argv)
    node: Node | None = None
    code = 1
    try:
        node = rclpy.create_node("calibrate_hand_client")
        client = node.create_client(Trigger, name)
        if not client.wait_for_service(timeout_sec=opts.timeout):
            print(
                f"calibrate_hand: service {name} is not available after {opts.timeout:g} s "
                "(is tracker_node running, with the same ROS_DOMAIN_ID and DDS settings?)",
                file=sys.stderr,
            )
            return 1
        future = client.call_async(Trigger.Request())
        rclpy.spin_until_future_complete(node, future, timeout_sec=opts.timeout + CALL_MARGIN_S)
        if not future.done():
            print(f"calibrate_hand: no answer from {name} within "
                  f"{opts.timeout + CALL_MARGIN_S:g} s", file=sys.stderr)
            return 1
        answer = future.result()
        if answer is None:
            print(f"calibrate_hand: the call to {name} failed: {future.exception()}", file=sys.stderr)
            return 1
        if answer.success:
            print(f"calibration succeeded: {answer.message}")
            code = 0
        else:
            print(f"calibration failed: {answer.message}", file=sys.stderr)
        return code
    except (KeyboardInterrupt, ExternalShutdownException):
        return 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
