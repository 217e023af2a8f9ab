"""SfM-TTR over a stream: keyframes, windows, live serving, diagnostics."""
