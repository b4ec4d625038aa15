"""The extractor node's ROS parameters and QoS: descriptors, type coercion, profiles.

The parameters themselves (names, types, defaults, ranges) are :data:`ppe_ros.ros.processing.PARAM_SPECS`.
"""

from __future__ import annotations

import array
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ppe_ros.ros.processing import PARAM_SPEC_BY_NAME, ROS_BUILTIN_PARAMETERS, ParamSpec

#: Prefix of rclpy's QoS override parameters (``qos_overrides.<topic>.<publisher|subscription>.<policy>``).
QOS_OVERRIDES_PREFIX = 'qos_overrides.'

_RELIABILITY = {'best_effort': ReliabilityPolicy.BEST_EFFORT, 'reliable': ReliabilityPolicy.RELIABLE}
_PARAMETER_TYPE = {
    'double': ParameterType.PARAMETER_DOUBLE,
    'integer': ParameterType.PARAMETER_INTEGER,
    'bool': ParameterType.PARAMETER_BOOL,
    'string': ParameterType.PARAMETER_STRING,
    'double_array': ParameterType.PARAMETER_DOUBLE_ARRAY,
}


def input_qos(reliability: str) -> QoSProfile:
    """QoS of the ``points`` subscription: keep last 1, volatile, the given reliability."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=_RELIABILITY[reliability],
                      durability=DurabilityPolicy.VOLATILE)


def output_qos() -> QoSProfile:
    """QoS of the plane outputs: reliable keep-last 1 (matches reliable and best-effort readers)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def parameter_descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """The ROS descriptor of a parameter: type, description, range or allowed values."""
    descriptor = ParameterDescriptor(
        name=spec.name,
        type=_PARAMETER_TYPE[spec.kind],
        description=spec.description,
        additional_constraints=spec.constraints(),
        read_only=spec.read_only,
    )
    if spec.kind == 'double' and spec.low is not None and spec.high is not None:
        descriptor.floating_point_range = [FloatingPointRange(from_value=float(spec.low),
                                                              to_value=float(spec.high), step=0.0)]
    elif spec.kind == 'integer' and spec.low is not None and spec.high is not None:
        descriptor.integer_range = [IntegerRange(from_value=int(spec.low), to_value=int(spec.high), step=1)]
    return descriptor


def as_declared_type(spec: ParamSpec, value: Any) -> Any:
    """Integers given for a double (array) parameter become floats (``-p max_error_increment:=1``).

    An integer array arrives as a list (``-p ray_origin:=[0,0,1]``) or, through the parameter
    service (``ros2 param set /extractor ray_origin "[0, 0, 1]"``), as an ``array.array('q')``.
    """
    if spec.kind == 'double' and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if spec.kind == 'double_array' and isinstance(value, list | tuple | array.array) and all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in value):
        return [float(v) for v in value]
    return value


def unknown_parameter_names(names: Any) -> list[str]:
    """Names given to the node (params file, ``-p``) that it does not have (ROS's own ones excepted)."""
    return sorted(
        str(name) for name in names
        if name not in PARAM_SPEC_BY_NAME and name not in ROS_BUILTIN_PARAMETERS
        and not str(name).startswith('qos_overrides')
    )


def metadata_qos() -> QoSProfile:
    """QoS of the sensor metadata subscription: reliable, transient local (the driver latches it), depth 1."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def qos_override_names(names: Any) -> list[str]:
    """The QoS override parameter names among ``names`` (params file, ``-p``)."""
    return sorted(str(name) for name in names if str(name).startswith(QOS_OVERRIDES_PREFIX))
