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
Declaring a node's parameter table with descriptors, and validating run-time changes (rclpy).

Everything decidable without rclpy is in :mod:`piezo_stage_ros.nodes.tables`; this module only
builds ``ParameterDescriptor`` messages from it and turns a refused change into a
``SetParametersResult`` with the reason.
"""

from __future__ import annotations

import array
from typing import Any, Callable, Sequence

from piezo_stage_ros.core.config.unknown import check_given, MULTI_AXIS_PREFIXES, ros_sources
from piezo_stage_ros.core.contracts.errors import PiezoStageError
from piezo_stage_ros.nodes.tables import Declaration, NodeTable
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

__all__ = ['ParameterBinding', 'check_undeclared', 'descriptor', 'multi_axis_hint']


def descriptor(decl: Declaration) -> ParameterDescriptor:
    """
    Return the descriptor of one parameter.

    Dynamic typing is on: an integer in a YAML file for a double parameter is accepted, and
    the types are checked by the table's own validation, which names parameter, value and range.
    """
    desc = ParameterDescriptor(name=decl.name, description=decl.description,
                               additional_constraints=decl.additional_constraints,
                               read_only=decl.read_only, dynamic_typing=True)
    if decl.float_range is not None:
        desc.floating_point_range = [FloatingPointRange(
            from_value=decl.float_range[0], to_value=decl.float_range[1], step=0.0)]
    if decl.int_range is not None:
        desc.integer_range = [IntegerRange(from_value=decl.int_range[0],
                                           to_value=decl.int_range[1], step=0)]
    return desc


def _plain(value: Any) -> Any:
    """Return ROS parameter values as plain Python (arrays become lists)."""
    if isinstance(value, (array.array, tuple)):
        return list(value)
    return value


class ParameterBinding:
    """
    A node's parameter table, declared on the node and kept validated.

    Parameters
    ----------
    node : Node
        The node to declare on.
    table : NodeTable
        Its parameter table.
    on_change : callable
        ``on_change(old, new)`` with the tuples of group objects, called for a change that
        validated; it may raise :class:`~piezo_stage_ros.core.contracts.errors.PiezoStageError` to
        refuse it (the reason goes back to the caller and nothing changes).

    Raises
    ------
    ParameterError
        If a start-up value is bad (the node cannot be built).

    """

    def __init__(self, node: Node, table: NodeTable,
                 on_change: Callable[[Sequence[Any], Sequence[Any]], None] | None = None
                 ) -> None:
        self.table = table
        self._on_change = on_change
        values: dict[str, Any] = {}
        for decl in table.declarations():
            param = node.declare_parameter(decl.name, decl.default, descriptor(decl))
            values[decl.name] = _plain(param.value)
        self.objects: tuple[Any, ...] = table.build(values)
        node.add_on_set_parameters_callback(self._on_set)

    def _on_set(self, params: list[Parameter]) -> SetParametersResult:
        changes = {p.name: _plain(p.value) for p in params}
        try:
            new = self.table.change(self.objects, changes)
            if self._on_change is not None:
                self._on_change(self.objects, new)
        except PiezoStageError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self.objects = new
        return SetParametersResult(successful=True)


def _declared(node: Node) -> set[str]:
    return set(node.list_parameters([], 0).names)


def check_undeclared(nodes: Sequence[Node], argv: Sequence[str]) -> None:
    """
    Refuse parameters given to the nodes of one process that they do not declare.

    ROS keeps what the parameter files and ``-p`` overrides give a node as its overrides and
    drops those it never declares; rclpy 7.1 has no public accessor for them, so they are read
    from the node's ``_parameter_overrides`` (empty where an rclpy lacks it: nothing refused).

    Parameters
    ----------
    nodes : sequence of Node
        The nodes of the process, built (their parameters declared).
    argv : sequence of str
        The command line the process was started with, to say where a value came from.

    Raises
    ------
    PiezoStageError
        Naming each parameter, its node, its source and the closest declared name.

    """
    sources = ros_sources(argv)
    declared = {node.get_name(): _declared(node) for node in nodes}
    messages: list[str] = []
    for node in nodes:
        name = node.get_name()
        others = set().union(*(d for n, d in declared.items() if n != name))
        given = getattr(node, '_parameter_overrides', {})
        try:
            check_given(name, given, declared[name], sources, others)
        except PiezoStageError as exc:
            messages.append(str(exc))
    if messages:
        raise PiezoStageError('; '.join(messages))


def multi_axis_hint(argv: Sequence[str]) -> str:
    """
    Return why a parameter file rcl could not read may be a multi-axis one, or ''.

    rcl's parser refuses a multi-axis file with bare axis names itself (``names: [x, y]``: it
    reads ``y`` as a boolean, and an array of mixed types is an error) before a node could
    read it; quoted names are strings.
    """
    try:
        sources = ros_sources(argv)
    except PiezoStageError:
        return ''
    for source in sources:
        names = [n for n in source.names if n.startswith(MULTI_AXIS_PREFIXES)]
        if names:
            return (f' ({source.where} has {names[0]!r}: a multi-axis stage; ROS reads a '
                    "bare axis name y or n as a boolean: quote the names, names: ['x', 'y'], "
                    "and a slow_axis: 'y')")
    return ''
