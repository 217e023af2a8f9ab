"""Stage 1 of SfM-TTR (Sec. 3.1): sparse SfM of a window with pycolmap."""
