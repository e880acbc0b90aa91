"""Command-line tools: bag evaluation, replay, sample-bag generation, benchmark.

Modules
-------
bagio
    Reading and writing depth / CameraInfo / ground-truth bags with ``rosbags``.
metrics
    The paper's fingertip error metrics (pure NumPy).
evaluate_bag, replay_bag, make_sample_bags, benchmark
    The console scripts of the same names.
"""
