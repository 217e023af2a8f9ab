"""The node's WARN when its metres go stale (core/metric/scale.py ``MetricStatus``): once metric,
the scale's source stopped (odometry silent for ``metric.odometry_timeout_s``, windows in a row
without a ground plane); the depth keeps the last metres, unchecked. Logged at once, then at
most once per the node's warning period while it lasts."""

from __future__ import annotations

from collections.abc import Callable


def warn_if_stale(ttr, warn_every: Callable[[str, str], None]) -> bool:
    """Warn (through the node's throttled ``warn_every``) when ``ttr``'s metric state is
    ``stale``; True when it is."""
    status = getattr(ttr, "metric_status", None)
    s = status() if status is not None else None
    if s is None or s.state != "stale":
        return False
    warn_every("metric_stale", f"depth no longer kept metric (metric.source {s.source}): "
               f"{s.reason}; the outputs keep the last {s.metres_per_unit:.4g} m per unit")
    return True
