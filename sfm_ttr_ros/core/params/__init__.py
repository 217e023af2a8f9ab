"""The ONE parameter schema of sfm_ttr_ros and the settings it builds.

:mod:`.schema` holds the table (one row per parameter), :mod:`.node` the node's own settings,
:mod:`.legacy` the old names that still work for one release, :mod:`.values` the checks, the
parameter files, ``--set`` and :func:`build`, :mod:`.docs` the reference page. This package
re-exports what callers use.
"""

from sfm_ttr_ros.core.params.docs import markdown_table, ros_literal
from sfm_ttr_ros.core.params.legacy import LEGACY
from sfm_ttr_ros.core.params.schema import PARAMS, SCHEMA, SECTIONS, TARGETS, Param
from sfm_ttr_ros.core.params.values import (
    Settings,
    build,
    check_value,
    defaults,
    parse_overrides,
    read_params_file,
    validate,
)

__all__ = ["LEGACY", "PARAMS", "SCHEMA", "SECTIONS", "TARGETS", "Param", "Settings", "build",
           "check_value", "defaults", "markdown_table", "parse_overrides", "read_params_file",
           "ros_literal", "validate"]
