"""
Node parameters declared once, from a typed spec, with descriptors a ROS user can read.

Each node lists its parameters as :class:`Param` records (name, default, description,
range, whether it may change at run time) and calls :func:`declare`. What that adds to
rclpy's own declaration:

- every parameter gets a ``ParameterDescriptor`` (description, range, ``read_only`` for
  start-up-only ones), so ``ros2 param describe`` says what it is and rclpy refuses values
  out of range with the reason;
- a float parameter accepts an integer (``-p fps:=30``), an integer-valued one given as a
  whole float, a float array accepts integers, and a fixed-length array one number for
  every element (``ros2 param set /pressure_bridge max_pressure_pa 50000``), at start-up
  and at run time (rclpy types a parameter by its default and would refuse them);
- ``dynamic=True`` keeps a parameter dynamically typed where a value may be either of two
  kinds (a camera ``source`` that is an index or a path);
- live parameters are applied through one callback: the node's ``check`` may refuse a
  change with a reason (e.g. a safety limit may only be lowered), and ``apply`` sees only
  accepted changes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.node import Node
from rclpy.parameter import Parameter

__all__ = ['Param', 'ParameterSet', 'ParameterTypeError', 'declare']


class ParameterTypeError(ValueError):
    """A parameter was given a value of a kind it cannot take; the message names it."""


@dataclass(frozen=True)
class Param:
    """
    One parameter: its name, default (which fixes its type), meaning and constraints.

    ``range`` is inclusive ``(low, high)``; for arrays it bounds every element.
    ``live`` parameters may be set at run time; all others are read-only after start-up.
    ``dynamic`` parameters take a string or an integer (a path or an index).
    ``length`` fixes the number of elements of an array parameter (one number is taken for
    all of them).
    ``choices`` lists the accepted values of a string parameter.
    """

    name: str
    default: Any
    description: str
    range: tuple | None = None
    live: bool = False
    dynamic: bool = False
    length: int | None = None
    choices: tuple = ()

    @property
    def type(self) -> Parameter.Type:
        """Return the ROS type that the default fixes (dynamic: NOT_SET)."""
        if self.dynamic:
            return Parameter.Type.NOT_SET
        return Parameter.Type.from_parameter_value(self.default)

    def descriptor(self) -> ParameterDescriptor:
        """Build the descriptor rclpy stores and ``ros2 param describe`` shows."""
        d = ParameterDescriptor(description=self.description, read_only=not self.live,
                                dynamic_typing=self.dynamic)
        notes = []
        if self.range is not None:
            lo, hi = self.range
            if self.type == Parameter.Type.INTEGER:
                d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
            elif self.type == Parameter.Type.DOUBLE:
                d.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                             to_value=float(hi), step=0.0)]
            else:
                notes.append(f'each element in [{lo}, {hi}]')
        if self.length is not None:
            notes.append(f'{self.length} elements')
        if self.choices:
            notes.append('one of: ' + ', '.join(map(str, self.choices)))
        if self.dynamic:
            notes.append('a string or an integer')
        if self.live:
            notes.append('may be set at run time')
        d.additional_constraints = '; '.join(notes)
        return d


_FLOAT = (Parameter.Type.DOUBLE,)
_NUMBER_TYPES = {
    Parameter.Type.DOUBLE: (int, float),
    Parameter.Type.INTEGER: (int,),
    Parameter.Type.DOUBLE_ARRAY: (int, float),
    Parameter.Type.INTEGER_ARRAY: (int,),
}


def _items(value) -> list | None:
    """Return the elements of a list-like value (rclpy gives arrays as ``array.array``)."""
    if isinstance(value, (str, bytes)) or not hasattr(value, '__len__'):
        return None
    return list(value)


def coerce(spec: Param, value: Any) -> Any:
    """
    Turn a value given for ``spec`` into its declared kind, or raise ParameterTypeError.

    Integers become floats for float parameters (and float arrays); a whole float becomes
    an integer for integer ones; strings and booleans are never converted.
    """
    t = spec.type
    where = f'parameter {spec.name!r}'
    if spec.dynamic:
        if isinstance(value, bool) or not isinstance(value, (int, str)):
            raise ParameterTypeError(f'{where}: expected a string or an integer, got '
                                     f'{value!r}')
        return value
    if t in (Parameter.Type.DOUBLE, Parameter.Type.INTEGER):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ParameterTypeError(f'{where}: expected a number, got {value!r}')
        if t == Parameter.Type.INTEGER:
            if isinstance(value, float) and not value.is_integer():
                raise ParameterTypeError(f'{where}: expected an integer, got {value!r}')
            return int(value)
        return float(value)
    if t in (Parameter.Type.DOUBLE_ARRAY, Parameter.Type.INTEGER_ARRAY):
        if spec.length and isinstance(value, (int, float)) and not isinstance(value, bool):
            value = [value] * spec.length        # `param set ... 50000`: every element
        items = _items(value)
        if items is None or any(isinstance(v, bool) or not isinstance(v, (int, float))
                                for v in items):
            raise ParameterTypeError(f'{where}: expected a list of numbers, got {value!r}')
        if t == Parameter.Type.INTEGER_ARRAY:
            if any(isinstance(v, float) and not v.is_integer() for v in items):
                raise ParameterTypeError(f'{where}: expected integers, got {value!r}')
            return [int(v) for v in items]
        return [float(v) for v in items]
    expected = type(spec.default)
    if expected is list:
        items = _items(value)
        if items is None or not all(isinstance(v, str) for v in items):
            raise ParameterTypeError(f'{where}: expected a list of strings, got {value!r}')
        return items
    if not isinstance(value, expected) or (expected is not bool and isinstance(value, bool)):
        raise ParameterTypeError(f'{where}: expected {expected.__name__}, got {value!r}')
    return value


def violation(spec: Param, value: Any) -> str:
    """Return why ``value`` breaks the spec's length, element range or choices ('' = fine)."""
    if spec.length is not None and len(value) != spec.length:
        return f'{spec.name} needs {spec.length} values, got {len(value)}'
    if spec.choices and value not in spec.choices:
        return f'{spec.name} must be one of {", ".join(map(str, spec.choices))}, got {value!r}'
    items = value if isinstance(value, list) else [value]
    if spec.range is not None and all(isinstance(v, (int, float)) for v in items):
        lo, hi = spec.range
        bad = [v for v in items if not (lo <= v <= hi) or
               (isinstance(v, float) and not math.isfinite(v))]
        if bad:
            return f'{spec.name} must be within [{lo}, {hi}], got {value!r}'
    return ''


class ParameterSet:
    """
    The declared values of one node, by attribute (``params.fps``), kept current.

    ``check(changes) -> str`` may refuse a run-time change with a reason ('' accepts);
    ``apply(changes)`` is called with the accepted changes, already coerced.
    """

    def __init__(self, node: Node, specs: Sequence[Param],
                 check: Callable[[dict], str] | None = None,
                 apply: Callable[[dict], None] | None = None):
        self._node = node
        self._specs = {s.name: s for s in specs}
        self._values: dict[str, Any] = {}
        self._check = check
        self._apply = apply
        for spec in specs:
            self._values[spec.name] = self._declare(spec)
        # rclpy concatenates what every pre-set callback returns: one per node, for all sets
        sets = node.__dict__.setdefault('_softshape_parameter_sets', [])
        if not sets:
            node.add_pre_set_parameters_callback(lambda ps: _pre_set_all(sets, ps))
        sets.append(self)
        node.add_on_set_parameters_callback(self._on_set)
        node.add_post_set_parameters_callback(self._post_set)

    def __getattr__(self, name: str) -> Any:
        values = self.__dict__.get('_values', {})
        if name in values:
            return values[name]
        raise AttributeError(f'no parameter {name!r}')

    def get(self, name: str) -> Any:
        """Return the current value of ``name``."""
        return self._values[name]

    def _declare(self, spec: Param) -> Any:
        """
        Declare dynamically first to see any override, then with the spec's own type.

        rclpy checks an override's type against the default's at declaration; going
        through a dynamically typed declaration lets an integer reach a float parameter.
        """
        node = self._node
        if spec.dynamic:
            value = node.declare_parameter(spec.name, spec.default, spec.descriptor()).value
            value = coerce(spec, value)
        else:
            probe = ParameterDescriptor(dynamic_typing=True)
            given = node.declare_parameter(spec.name, spec.default, probe).value
            value = coerce(spec, given)
            node.undeclare_parameter(spec.name)
            value = node.declare_parameter(spec.name, value, spec.descriptor(),
                                           ignore_override=True).value
        why = violation(spec, value)
        if why:
            raise ParameterTypeError(f'parameter {why}')
        return value

    # -- run time ---------------------------------------------------------------------------
    def convert(self, p: Parameter) -> Parameter:
        """Give an integer for a float parameter as a float, before rclpy's type check."""
        spec = self._specs.get(p.name)
        if spec is not None and not spec.dynamic and spec.type in _NUMBER_TYPES:
            try:
                return Parameter(p.name, value=coerce(spec, p.value))
            except ParameterTypeError:
                pass                     # rclpy refuses it with its own reason
        return p

    def _on_set(self, parameters: list[Parameter]) -> SetParametersResult:
        changes = {}
        for p in parameters:
            spec = self._specs.get(p.name)
            if spec is None:
                continue                 # not ours (e.g. use_sim_time, the updater's)
            try:
                value = coerce(spec, p.value)
            except ParameterTypeError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
            why = violation(spec, value)
            if why:
                return SetParametersResult(successful=False, reason=why)
            changes[p.name] = value
        if changes and self._check is not None and self._values:
            why = self._check(changes)
            if why:
                self._node.get_logger().warning(f'parameter change refused: {why}')
                return SetParametersResult(successful=False, reason=why)
        return SetParametersResult(successful=True)

    def _post_set(self, parameters: list[Parameter]) -> None:
        changes = {p.name: coerce(self._specs[p.name], p.value) for p in parameters
                   if p.name in self._specs and p.name in self._values}
        if not changes:
            return                       # a declaration, not a change
        self._values.update(changes)
        if self._apply is not None:
            self._apply(changes)


def _pre_set_all(sets: list, parameters: list[Parameter]) -> list[Parameter]:
    out = []
    for p in parameters:
        for ps in sets:
            p = ps.convert(p)
        out.append(p)
    return out


def declare(node: Node, specs: Sequence[Param], check: Callable[[dict], str] | None = None,
            apply: Callable[[dict], None] | None = None) -> ParameterSet:
    """Declare ``specs`` on ``node`` and return their values (see :class:`ParameterSet`)."""
    return ParameterSet(node, specs, check, apply)
