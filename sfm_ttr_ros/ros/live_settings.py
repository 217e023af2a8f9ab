"""The ``refiner`` node's settings from its parameters, kept current as they change
(docs/node.md, "Parameters").

At start-up every parameter of the schema is declared (:mod:`sfm_ttr_ros.ros.params`) and
checked: an invalid set stops the start with an :class:`InputError`. Then every setting is
rebuilt once per parameter change (not per frame or window): the stream and the window read
theirs from :attr:`LiveSettings.all`, the node its own (``all.node``). The on-set check never
raises (an exception would reach the parameter service): anything unexpected refuses the change
with the reason and counts a fault.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rcl_interfaces.msg import SetParametersResult

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.params import Settings
from sfm_ttr_ros.core.pipeline import TTRConfig
from sfm_ttr_ros.ros import params as node_params


class LiveSettings:
    """``node``'s parameters declared, checked and built into :attr:`all`; ``check_config``
    checks a window config against the model (raises :class:`InputError`), ``fault(place,
    exc)`` counts an unexpected exception, ``warn_every(key, message)`` logs throttled."""

    def __init__(self, node, *, check_config: Callable[[TTRConfig], None],
                 fault: Callable[[str, BaseException], None],
                 warn_every: Callable[[str, str], None]) -> None:
        self._node = node
        self._check_config, self._fault, self._warn_every = check_config, fault, warn_every
        node_params.declare(node)
        self.start_values = node_params.current_values(node)
        reason = node_params.validate(self.start_values)
        if reason:
            raise InputError(f"invalid parameters: {reason}")
        self.all: Settings = node_params.build_settings(self.start_values)
        for warning in self.all.warnings:
            node.get_logger().warning(warning)
        node.add_on_set_parameters_callback(self.check_change)
        node.add_post_set_parameters_callback(self.changed)

    def values(self) -> dict[str, Any]:
        """The parameters' current values."""
        return node_params.current_values(self._node)

    def changed(self, params) -> None:
        """After a change: every setting again (and the legacy names' warnings)."""
        try:
            settings = node_params.build_settings(self.values())
        except Exception as exc:  # validated before it was set: unexpected
            self._fault("parameters", exc)
            return
        self.all = settings
        for warning in settings.warnings:
            self._warn_every(f"legacy:{warning}", warning)

    def check_change(self, params) -> SetParametersResult:
        """The on-set check of ``params``: refused with the reason when the values they make
        are invalid or the model cannot take the config."""
        try:
            values = self.values()
            values.update({p.name: p.value for p in params})
            reason = node_params.validate(values)
            if not reason:
                self._check_config(node_params.build_ttr_config(values))
        except InputError as exc:  # e.g. frozen encoder levels on a model without stages
            reason = str(exc)
        except Exception as exc:  # a value no check foresaw: refuse it, with the reason
            reason = f"{type(exc).__name__}: {exc}"
            self._fault("parameters", exc)
        if reason:
            self._warn_every("parameters", f"parameter change refused: {reason}")
        return SetParametersResult(successful=not reason, reason=reason)
