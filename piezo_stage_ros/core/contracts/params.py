# Copyright 2026 piezo_stage_ros maintainers
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""
Declarative, self-validating parameter objects.

A parameter group is a frozen dataclass that derives from :class:`Params` and declares each field
with :func:`param` (a value with unit, range and description) or :func:`group` (a nested group).
From that one declaration come:

- validation in ``__post_init__`` (type, finiteness, range, choices, then the group's own
  cross-field rules in ``_check``), raising :class:`ParameterError` that names the parameter,
  the value and the allowed range;
- :meth:`Params.from_flat` / :meth:`Params.to_flat`, the mapping to and from dotted ROS parameter
  names (``'rac.epsilon'``), used by the YAML loader and by the nodes;
- :meth:`Params.specs`, the table (name, type, default, unit, range, description, read-only) from
  which a node declares its ROS parameters with descriptors and docs/parameters.md documents them.

Parameter objects live beside the code they configure; this module knows none of them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
import math
import typing
from typing import Any, ClassVar, Mapping, TypeVar

from piezo_stage_ros.core.contracts.errors import ParameterError

__all__ = ['Params', 'ParamSpec', 'group', 'param']

_P = TypeVar('_P', bound='Params')


@dataclass(frozen=True)
class ParamSpec:
    """
    Description of one scalar parameter, as a node declares it.

    Attributes
    ----------
    name : str
        Dotted name (with the prefix of every enclosing group).
    type_name : str
        One of ``'double'``, ``'integer'``, ``'bool'``, ``'string'``, ``'double_array'``
        (the ROS parameter type names).
    default : Any
        Default value.
    unit : str
        Physical unit (``'m'``, ``'V'``, ``'s'``, ``'-'`` for dimensionless).
    description : str
        One sentence.
    low, high : float or None
        Range bounds, ``None`` when unbounded on that side.
    low_open, high_open : bool
        Whether the bound itself is excluded.
    choices : tuple of str or None
        Allowed strings for a string parameter.
    read_only : bool
        Whether the parameter may only be set at start-up.

    """

    name: str
    type_name: str
    default: Any
    unit: str
    description: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple[str, ...] | None = None
    read_only: bool = False

    def allowed(self) -> str:
        """Return the allowed values in words, e.g. ``'(0, inf)'`` or ``"one of 'a', 'b'"``."""
        if self.choices is not None:
            return 'one of ' + ', '.join(repr(c) for c in self.choices)
        if self.type_name == 'bool':
            return 'true or false'
        if self.type_name == 'string':
            return 'any string'
        lo = '-inf' if self.low is None else f'{self.low:g}'
        hi = 'inf' if self.high is None else f'{self.high:g}'
        left = '(' if self.low_open or self.low is None else '['
        right = ')' if self.high_open or self.high is None else ']'
        kind = 'finite integer in ' if self.type_name == 'integer' else 'finite number in '
        if self.type_name == 'double_array':
            kind = 'non-empty list of finite numbers, each in '
        return f'{kind}{left}{lo}, {hi}{right}'

    def validate(self, value: Any) -> Any:
        """
        Check one value against this spec and return it in canonical form.

        Ints are accepted where a float is expected (and converted); lists where a tuple of
        floats is expected. Booleans are never accepted as numbers.

        Raises
        ------
        ParameterError
            If the value has the wrong type, is not finite, is out of range or not a choice.

        """
        if self.type_name == 'bool':
            if not isinstance(value, bool):
                raise ParameterError(self.name, value, self.allowed(), 'is not a boolean')
            return value
        if self.type_name == 'string':
            if not isinstance(value, str):
                raise ParameterError(self.name, value, self.allowed(), 'is not a string')
            if self.choices is not None and value not in self.choices:
                raise ParameterError(self.name, value, self.allowed(), 'is not a valid choice')
            return value
        if self.type_name == 'double_array':
            if isinstance(value, (str, bytes)) or not hasattr(value, '__iter__'):
                raise ParameterError(self.name, value, self.allowed(), 'is not a list')
            items = tuple(self._number(v, float) for v in value)
            if not items:
                raise ParameterError(self.name, value, self.allowed(), 'is empty')
            return items
        return self._number(value, int if self.type_name == 'integer' else float)

    def _number(self, value: Any, kind: type) -> Any:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            # numpy scalars are accepted through float(); strings and others are not
            try:
                import numpy as np
                if isinstance(value, np.generic) and not isinstance(value, np.bool_):
                    value = value.item()
                else:
                    raise TypeError
            except TypeError:
                raise ParameterError(self.name, value, self.allowed(), 'is not a number') from None
        if kind is int:
            if isinstance(value, float):
                if not value.is_integer():
                    raise ParameterError(self.name, value, self.allowed(), 'is not an integer')
                value = int(value)
        else:
            value = float(value)
        if isinstance(value, float) and not math.isfinite(value):
            raise ParameterError(self.name, value, self.allowed(), 'is not finite')
        if self.low is not None and (value < self.low or (self.low_open and value == self.low)):
            raise ParameterError(self.name, value, self.allowed())
        if self.high is not None and (value > self.high
                                      or (self.high_open and value == self.high)):
            raise ParameterError(self.name, value, self.allowed())
        return value


def param(default: Any, *, unit: str, description: str, low: float | None = None,
          high: float | None = None, low_open: bool = False, high_open: bool = False,
          choices: tuple[str, ...] | None = None, read_only: bool = False) -> Any:
    """
    Declare a scalar (or float-list) parameter field of a :class:`Params` dataclass.

    Parameters
    ----------
    default : Any
        Default value; its type must match the field annotation.
    unit : str
        Physical unit; ``'-'`` when dimensionless.
    description : str
        One sentence shown in ROS parameter descriptors and docs/parameters.md.
    low, high : float, optional
        Range bounds (inclusive unless ``low_open`` / ``high_open``).
    low_open, high_open : bool
        Exclude the bound itself.
    choices : tuple of str, optional
        Allowed values of a string parameter.
    read_only : bool
        Only settable at start-up (node parameter descriptor ``read_only``).

    Returns
    -------
    dataclasses.Field
        The field, carrying its metadata.

    """
    meta = {'unit': unit, 'description': description, 'low': low, 'high': high,
            'low_open': low_open, 'high_open': high_open, 'choices': choices,
            'read_only': read_only}
    return field(default=default, metadata={'param': meta})


def group(cls: type[_P], description: str) -> Any:
    """
    Declare a nested parameter group field (its names get the field name as prefix).

    Parameters
    ----------
    cls : type
        The :class:`Params` subclass of the group; its defaults are the field default.
    description : str
        What the group configures.

    Returns
    -------
    dataclasses.Field
        The field.

    """
    return field(default_factory=cls, metadata={'group': description})


_TYPE_NAMES = {float: 'double', int: 'integer', bool: 'bool', str: 'string'}


class Params:
    """
    Base class of frozen, self-validating parameter dataclasses.

    Subclasses are declared ``@dataclass(frozen=True)`` with :func:`param` / :func:`group`
    fields and may override :meth:`_check` for rules that involve several fields (raise
    :class:`ParameterError` naming the field that must change).
    """

    _spec_cache: ClassVar[dict[type, dict[str, ParamSpec | type[Params]]]] = {}

    def __post_init__(self) -> None:
        for name, spec in self._field_specs().items():
            value = getattr(self, name)
            if isinstance(spec, ParamSpec):
                checked = spec.validate(value)
                if checked is not value:
                    object.__setattr__(self, name, checked)
            elif not isinstance(value, spec):
                raise ParameterError(name, value, f'a {spec.__name__}', 'has the wrong type')
        self._check()

    def _check(self) -> None:
        """Cross-field rules; the default has none."""

    @classmethod
    def _field_specs(cls) -> dict[str, ParamSpec | type[Params]]:
        cached = Params._spec_cache.get(cls)
        if cached is not None:
            return cached
        hints = typing.get_type_hints(cls)
        specs: dict[str, ParamSpec | type[Params]] = {}
        for f in dataclasses.fields(cls):  # type: ignore[arg-type]
            hint = hints[f.name]
            if 'group' in f.metadata:
                specs[f.name] = hint
                continue
            meta = f.metadata.get('param')
            if meta is None:
                raise TypeError(f'{cls.__name__}.{f.name} is not declared with param() or group()')
            if typing.get_origin(hint) is tuple:
                type_name = 'double_array'
            else:
                type_name = _TYPE_NAMES[hint]
            specs[f.name] = ParamSpec(name=f.name, type_name=type_name, default=f.default,
                                      **meta)
        Params._spec_cache[cls] = specs
        return specs

    @classmethod
    def specs(cls, prefix: str = '') -> list[ParamSpec]:
        """
        Return the flat table of every scalar parameter, groups expanded with dotted names.

        Parameters
        ----------
        prefix : str
            Prepended to every name (e.g. ``'controller.'``).

        Returns
        -------
        list of ParamSpec
            In declaration order.

        """
        rows: list[ParamSpec] = []
        for name, spec in cls._field_specs().items():
            if isinstance(spec, ParamSpec):
                rows.append(dataclasses.replace(spec, name=prefix + name))
            else:
                rows.extend(spec.specs(prefix + name + '.'))
        return rows

    @classmethod
    def from_flat(cls: type[_P], values: Mapping[str, Any], *, prefix: str = '',
                  strict: bool = True) -> _P:
        """
        Build the group from a flat mapping of dotted names to values.

        Parameters
        ----------
        values : Mapping[str, Any]
            E.g. ``{'rac.epsilon': 0.05}``; names missing from it keep their defaults.
        prefix : str
            Only keys starting with this prefix are read (it is stripped first); it also prefixes
            the names in error messages.
        strict : bool
            Refuse keys under ``prefix`` that name no parameter of the group.

        Returns
        -------
        Params
            The validated group.

        Raises
        ------
        ParameterError
            On the first bad or unknown value, naming it with its full dotted name.

        """
        local = {k[len(prefix):]: v for k, v in values.items() if k.startswith(prefix)}
        if strict:
            known = {s.name for s in cls.specs()}
            for key in local:
                if key not in known:
                    raise ParameterError(prefix + key, local[key],
                                         'a known parameter name (see docs/parameters.md)',
                                         'is not a parameter of this node')
        return cls._build(local, prefix)

    @classmethod
    def _build(cls: type[_P], local: Mapping[str, Any], prefix: str) -> _P:
        kwargs: dict[str, Any] = {}
        for name, spec in cls._field_specs().items():
            if isinstance(spec, ParamSpec):
                if name in local:
                    kwargs[name] = local[name]
            else:
                sub = {k[len(name) + 1:]: v for k, v in local.items()
                       if k.startswith(name + '.')}
                kwargs[name] = spec._build(sub, prefix + name + '.')
        try:
            return cls(**kwargs)
        except ParameterError as exc:
            raise exc.with_prefix(prefix) from None

    def to_flat(self, prefix: str = '') -> dict[str, Any]:
        """Return ``{dotted name: value}`` for every scalar parameter (tuples become lists)."""
        out: dict[str, Any] = {}
        for name, spec in self._field_specs().items():
            value = getattr(self, name)
            if isinstance(spec, ParamSpec):
                out[prefix + name] = list(value) if isinstance(value, tuple) else value
            else:
                out.update(value.to_flat(prefix + name + '.'))
        return out

    def replace(self: _P, **changes: Any) -> _P:
        """Return a validated copy with some fields changed (like ``dataclasses.replace``)."""
        return dataclasses.replace(self, **changes)  # type: ignore[type-var]

    def with_flat(self: _P, values: Mapping[str, Any], *, prefix: str = '') -> _P:
        """
        Return a validated copy with some parameters changed by dotted name.

        Parameters
        ----------
        values : Mapping[str, Any]
            New values; only keys starting with ``prefix`` are read.
        prefix : str
            Prefix of the group's names in ``values`` and in error messages.

        Returns
        -------
        Params
            The changed copy; ``self`` is left as it is.

        """
        merged = {prefix + k: v for k, v in self.to_flat().items()}
        merged.update({k: v for k, v in values.items() if k.startswith(prefix)})
        return type(self).from_flat(merged, prefix=prefix)
