"""Many sequences in one command (``sfm-ttr benchmark --split FILE``, ``sfm-ttr run --split
FILE``), on this machine or on a Ray cluster (docs/cluster.md).

One module per concern, each small:

* :mod:`.spec` the split file: one sequence per line (KITTI drives, image folders with K,
  rosbag2 bags, or the KITTI Eigen split's own lines), parsed into :class:`.spec.SequenceSpec`;
* :mod:`.sources` a spec opened as an :class:`~sfm_ttr_ros.data.sequence.ImageSequence` and the
  frames to run and to evaluate;
* :mod:`.task` one sequence's work (the benchmark's or ``run``'s own functions), returned as
  files and a row: what a worker executes;
* :mod:`.cache` the resume store: a sequence's results are kept under a key of its line, the
  settings and the code, and are not computed again for the same key;
* :mod:`.engine` where the tasks run: in this process, or as Ray tasks (local instance or a
  cluster), with bounded retries of a worker that died, and Ctrl-C;
* :mod:`.progress` a tqdm bar on a terminal, log lines otherwise;
* :mod:`.report` the split's results: one row per sequence, metrics pooled over every evaluated
  frame, the per-frame CSV of every sequence;
* :mod:`.command` the command-line options and the command itself.
"""
