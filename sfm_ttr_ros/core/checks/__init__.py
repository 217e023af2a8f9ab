"""The window checks: a window judged before, while and after it refines."""
