"""sfm_ttr_ros: SfM-TTR (Izquierdo & Civera, CVPR 2023) test-time refinement of single-view
depth networks, as a ROS-free core library with a thin ROS 2 node on top."""

__version__ = "0.1.0"
