"""SfM features in torch (``sfm.features: torch``): SIFT, matching, the COLMAP database."""
