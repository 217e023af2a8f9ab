"""Stage 3 of SfM-TTR (Sec. 3.2, Eq. (4)): the network's depth aligned to SfM's."""
