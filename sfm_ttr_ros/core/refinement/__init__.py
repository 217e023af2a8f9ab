"""Stage 4 of SfM-TTR (Sec. 3.3, Eq. (5)): test-time refinement of the encoder."""
