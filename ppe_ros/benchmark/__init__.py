"""Benchmark suite: SynPEB-style data sets, plane-extraction methods behind one interface, evaluation, tuning.

* :mod:`ppe_ros.benchmark.dataset`: ``make_dataset`` writes SynPEB-format scans (train/test x noise level).
* :mod:`ppe_ros.benchmark.methods`: the ``PlaneMethod`` interface (points -> labels, timed) with PPE and
  MSAC; :mod:`ppe_ros.benchmark.peers`: optional peers (Open3D, Polylidar3D), skipped when absent.
* :mod:`ppe_ros.benchmark.runner`: run methods over scans and score them with the paper's metrics.
* :mod:`ppe_ros.benchmark.report`: the paper's table as text/markdown and the f-over-sqrt(e) plot.
* :mod:`ppe_ros.benchmark.tuning`: grid search of PPE's lmax x e on a train split.
"""
