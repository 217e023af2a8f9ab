"""The ONE parameter schema of sfm_ttr_ros and the settings it builds (see :mod:`.schema`)."""

from sfm_ttr_ros.core.params.schema import (
    PARAMS,
    RENAMED,
    SCHEMA,
    SECTIONS,
    TARGETS,
    Param,
    Settings,
    build,
    check_value,
    defaults,
    markdown_table,
    parse_overrides,
    read_params_file,
    ros_literal,
    validate,
)

__all__ = ["PARAMS", "RENAMED", "SCHEMA", "SECTIONS", "TARGETS", "Param", "Settings", "build",
           "check_value", "defaults", "markdown_table", "parse_overrides", "read_params_file",
           "ros_literal", "validate"]
