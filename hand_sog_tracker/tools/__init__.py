"""Command-line tools and what they share: evaluation, the node harness, replay, sample bags.

Console scripts (``setup.py``)
------------------------------
``ros2 run hand_sog_tracker <name>``; a pip install names them ``hand_sog_<name>``.

evaluate_bag
    Score the tracker on bags with fingertip ground truth (core mode or ``--through-node``).
replay_bag
    Publish a bag's topics live, a stand-in for ``ros2 bag play``.
make_sample_bags
    Write the deterministic synthetic sample bags of ``bags/``.
benchmark
    Per-stage speed of the core tracker on one core.
demo
    Run ``tracker_node`` on a bundled bag and show what it does (``make demo``).

Modules they share
------------------
bagio
    Reading and writing depth / CameraInfo / ground-truth bags with ``rosbags`` (no ROS needed;
    topic names and message conversions from :mod:`hand_sog_tracker.interface`).
bagwrite
    Writing them (``BagWriter``, ``write_depth_bag``; re-exported by ``bagio``).
bagmsgs
    The bag convention's topics and types and the rosbags message builders (re-exported by ``bagio``).
bagset
    Which bags to evaluate: bags and folders of bags with their ``hand_sog_sample.json`` sidecar.
evaluation
    Core-mode evaluation of one bag: the core tracker on every depth image, scored.
node_eval
    ``evaluate_bag --through-node``: the node scored by replaying a bag to it over loopback DDS.
node_harness
    ``tracker_node`` as a child process on loopback DDS, fed frames and listened to
    (used by ``node_eval``, ``demo`` and the node tests).
node_process
    The node as a child process; DDS confined to this machine (``loopback_dds``).
records
    Evaluation records: per-frame outcomes, one bag's evaluation, pooled totals, progress bar.
metrics
    The paper's fingertip error metrics (pure NumPy).
report
    Text tables and JSON of an evaluation.
figures
    The error plot (matplotlib, optional) and overlays of the worst frames.
tracker_params
    Tracker settings for the tools: the node's params YAML, ``--set name=value``, ``--handedness``.
"""
