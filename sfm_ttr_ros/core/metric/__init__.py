"""Metric scale: the factor that turns the network's depth units into metres (not in the paper).

SfM and a monocular network are both up to scale. One known length makes them metric: the
camera's height above a ground plane the window's SfM points lie on (:mod:`.ground`), the
distance an odometry source says the camera travelled (:mod:`.odometry`), or a factor the user
knows. :mod:`.scale` turns each window's estimate into one steady factor for the outputs.
"""
