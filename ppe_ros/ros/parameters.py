"""The extractor node's ROS parameters and QoS: declaration, descriptors, type coercion, callbacks, profiles.

The parameters themselves (names, types, defaults, ranges) are :data:`ppe_ros.ros.processing.PARAM_SPECS`.
"""

from __future__ import annotations

import array
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.exceptions import ParameterException, ParameterNotDeclaredException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ppe_ros.ros.processing import (
    PARAM_SPEC_BY_NAME,
    PARAM_SPECS,
    ROS_BUILTIN_PARAMETERS,
    ExtractorParams,
    ParamSpec,
)

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
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=1,
        reliability=_RELIABILITY[reliability],
        durability=DurabilityPolicy.VOLATILE,
    )


def output_qos() -> QoSProfile:
    """QoS of the plane outputs: reliable keep-last 1 (matches reliable and best-effort readers)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


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
        descriptor.floating_point_range = [
            FloatingPointRange(from_value=float(spec.low), to_value=float(spec.high), step=0.0)
        ]
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
    if (
        spec.kind == 'double_array'
        and isinstance(value, list | tuple | array.array)
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ):
        return [float(v) for v in value]
    return value


def unknown_parameter_names(names: Any) -> list[str]:
    """Names given to the node (params file, ``-p``) that it does not have (ROS's own ones excepted)."""
    return sorted(
        str(name)
        for name in names
        if name not in PARAM_SPEC_BY_NAME
        and name not in ROS_BUILTIN_PARAMETERS
        and not str(name).startswith('qos_overrides')
    )


def metadata_qos() -> QoSProfile:
    """QoS of the sensor metadata subscription: reliable, transient local (the driver latches it), depth 1."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


def qos_override_names(names: Any) -> list[str]:
    """The QoS override parameter names among ``names`` (params file, ``-p``)."""
    return sorted(str(name) for name in names if str(name).startswith(QOS_OVERRIDES_PREFIX))


def check_numba_threads(count: int) -> None:
    """Raise ValueError for a ``numba_threads`` above the threads numba has (``NUMBA_NUM_THREADS``)."""
    import numba

    if count > numba.config.NUMBA_NUM_THREADS:
        raise ValueError(
            f'numba_threads must be 0 (all) or at most {numba.config.NUMBA_NUM_THREADS} '
            f'(NUMBA_NUM_THREADS); got {count}'
        )


def declare_extractor_parameters(node: Node) -> ExtractorParams:
    """Declare every parameter of :data:`PARAM_SPECS` on ``node`` (with descriptors) and validate them.

    Integers given for doubles are converted first; names the node does not have are warned about.

    Raises:
        ValueError: a value given at start-up is invalid (the message names the parameter).
    """
    overrides = getattr(node, '_parameter_overrides', {})
    values = {}
    for spec in PARAM_SPECS:
        override = overrides.get(spec.name)
        if override is not None:
            coerced = as_declared_type(spec, override.value)
            if coerced is not override.value:
                overrides[spec.name] = Parameter(spec.name, value=coerced)
        default = list(spec.default) if spec.kind == 'double_array' else spec.default
        try:
            value = node.declare_parameter(spec.name, default, parameter_descriptor(spec)).value
            values[spec.name] = spec.validate(value)
        except (ParameterException, ValueError) as exc:
            raise ValueError(f'invalid parameter {spec.name!r}: {exc}') from None
    try:
        params = ExtractorParams(**values)
        check_numba_threads(params.numba_threads)
    except ValueError as exc:
        raise ValueError(f'invalid parameters: {exc}') from None
    unknown = unknown_parameter_names(overrides)
    if unknown:
        node.get_logger().warning(
            f'ignoring unknown parameter(s) {unknown} (a typo in the params file?); known: {sorted(PARAM_SPEC_BY_NAME)}'
        )
    return params


def coerce_parameters(node: Node, parameters: list[Parameter]) -> list[Parameter]:
    """Pre-set callback: refuse names ``node`` does not have (naming them), convert integers given for doubles."""
    unknown = sorted(p.name for p in parameters if not node.has_parameter(p.name))
    if unknown:  # rclpy's own message would be "Invalid access to undeclared parameter(s): []"
        raise ParameterNotDeclaredException(
            f'{unknown}: the extractor has no such parameter; known: {sorted(PARAM_SPEC_BY_NAME)}'
        )
    out = []
    for parameter in parameters:
        spec = PARAM_SPEC_BY_NAME.get(parameter.name)
        value = parameter.value
        coerced = value if spec is None else as_declared_type(spec, value)
        out.append(parameter if coerced is value else Parameter(parameter.name, value=coerced))
    return out


def parameter_changes(parameters: list[Parameter]) -> dict[str, Any]:
    """Name -> value of the extractor's own parameters among ``parameters`` (ROS's and QoS ones left out)."""
    return {p.name: p.value for p in parameters if p.name in PARAM_SPEC_BY_NAME}


def validate_parameter_changes(params: ExtractorParams, parameters: list[Parameter]) -> SetParametersResult:
    """On-set callback: accept ``parameters`` if ``params`` with them is valid, else refuse with the reason."""
    try:
        changed = params.replace(**parameter_changes(parameters))
        check_numba_threads(changed.numba_threads)
    except ValueError as exc:
        return SetParametersResult(successful=False, reason=str(exc))
    return SetParametersResult(successful=True)
