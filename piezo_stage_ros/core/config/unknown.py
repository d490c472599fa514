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
Parameters given to a node that it does not declare (rclpy-free).

ROS hands a node every value of its parameter files' sections (its own and ``/**``) and of the
``-p`` overrides, and the node keeps only the names it declares: a misspelt name would run with
its default without a word. The nodes compare what they were given with what they declared
(:func:`check_given`) before their loop starts; this module finds where each name came from on
the command line (:func:`ros_sources`) and words the refusal, with the closest declared name.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Collection, Iterable, Sequence

from piezo_stage_ros.core.config.loader import load_config, WILDCARD
from piezo_stage_ros.core.config.nodes import closest_name
from piezo_stage_ros.core.contracts.errors import ConfigError

__all__ = ['check_given', 'MULTI_AXIS_PREFIXES', 'ros_options', 'ros_sources', 'RosSource',
           'unknown_given']

# what ROS itself reads on every node (declared by rclpy, or only on request)
_ALWAYS = frozenset({'use_sim_time'})
_ALWAYS_PREFIXES = ('qos_overrides.',)
# the multi-axis sections of a parameter file, read by the offline runner alone
MULTI_AXIS_PREFIXES = ('axes.', 'scan.')


@dataclass(frozen=True)
class RosSource:
    """
    One place of a ROS command line that gives parameters.

    Attributes
    ----------
    where : str
        In words, e.g. ``"-p rac.gama:=100"`` or ``"config/a.yaml, section 'controller_node'"``.
    node : str
        The node name it is for, or ``'/**'`` for every node of the process.
    names : tuple of str
        The dotted parameter names it gives.

    """

    where: str
    node: str
    names: tuple[str, ...]


def ros_options(argv: Sequence[str]) -> list[tuple[str, str]]:
    """
    Return the ``(flag, value)`` pairs of a ROS command line's ``--params-file`` and ``-p``.

    Only the parts between ``--ros-args`` and ``--`` (or the end) are ROS arguments.
    """
    pairs: list[tuple[str, str]] = []
    ros = False
    args = list(argv)
    i = 0
    while i < len(args):
        arg = args[i]
        if arg == '--ros-args':
            ros = True
        elif arg == '--':
            ros = False
        elif ros and arg in ('--params-file', '-p', '--param') and i + 1 < len(args):
            pairs.append((arg, args[i + 1]))
            i += 1
        i += 1
    return pairs


def ros_sources(argv: Sequence[str]) -> list[RosSource]:
    """
    Return the parameter files' sections and the ``-p`` overrides of a ROS command line.

    Parameters
    ----------
    argv : sequence of str
        The command line; only the parts between ``--ros-args`` and ``--`` (or the end) count.

    Returns
    -------
    list of RosSource
        The files' sections in order, then the overrides in order, as rcl reads them (a
        node's own entries win over wildcard ones, and among those the last one).

    Raises
    ------
    ConfigError
        If a parameter file cannot be read or is not shaped as ROS reads it.

    """
    files: list[RosSource] = []
    overrides: list[RosSource] = []
    for flag, value in ros_options(argv):
        if flag == '--params-file':
            for section, values in load_config([value]).sections.items():
                files.append(RosSource(f'{value}, section {section!r}', section,
                                       tuple(values)))
        elif flag in ('-p', '--param'):
            node, _, name = value.split(':=', 1)[0].rpartition(':')
            overrides.append(RosSource(f'{flag} {value}', node or WILDCARD, (name,)))
    return files + overrides


def _accepted(name: str, declared: Collection[str]) -> bool:
    return name in declared or name in _ALWAYS or name.startswith(_ALWAYS_PREFIXES)


def unknown_given(node: str, given: Iterable[str], declared: Collection[str],
                  sources: Sequence[RosSource] = (), others: Collection[str] = ()
                  ) -> list[str]:
    """
    Return one sentence per parameter given to a node that it does not declare.

    Parameters
    ----------
    node : str
        The node's name, e.g. ``'controller_node'``.
    given : iterable of str
        The names ROS gave the node (its parameter overrides).
    declared : collection of str
        The names the node declared (its table and what rclpy declares itself).
    sources : sequence of RosSource
        The command line's sources (:func:`ros_sources`), to say where a name came from.
    others : collection of str
        Names the other nodes of the same process declare: a value given to every node (a
        ``/**`` section, ``-p name:=value``) is meant for one of them and is accepted.

    Returns
    -------
    list of str
        Empty when every name is declared; the multi-axis names of a node in one sentence.

    """
    messages: list[str] = []
    multi_axis: list[str] = []
    for name in sorted(set(given)):
        if _accepted(name, declared):
            continue
        # a node's own section wins over a wildcard one, and the last of each kind
        from_ = ([s for s in sources if name in s.names and s.node == WILDCARD]
                 + [s for s in sources if name in s.names and s.node == node])
        if others and name in others and all(s.node == WILDCARD for s in from_):
            continue
        where = f'from {from_[-1].where}' if from_ else 'from its parameter overrides'
        if name.startswith('scan.') and node != 'trajectory_node':
            messages.append(f"{node}: parameter {name!r} ({where}) is the trajectory node's "
                            '(trajectory_node scan.*), not a parameter of this node')
            continue
        if name.startswith(MULTI_AXIS_PREFIXES):
            multi_axis.append(f'{name!r} ({where})')
            continue
        close = closest_name(name, declared)
        hint = f"; did you mean '{close}'?" if close else ''
        messages.append(f'{node}: parameter {name!r} ({where}) is not a parameter of this '
                        f'node{hint} (its parameters: docs/reference/ros-interface.md)')
    if multi_axis:
        messages.insert(0, f'{node}: ' + ', '.join(multi_axis) + ' describe a multi-axis '
                        'stage, which the nodes run when their parameter files '
                        'give plant_node axes.names, and offline (python -m '
                        'piezo_stage_ros.simulate --config FILE); these reached a one-axis '
                        'node: give the nodes the whole multi-axis file')
    return messages


def check_given(node: str, given: Iterable[str], declared: Collection[str],
                sources: Sequence[RosSource] = (), others: Collection[str] = ()) -> None:
    """
    Refuse the parameters :func:`unknown_given` finds.

    Raises
    ------
    ConfigError
        Naming each of them, the node and where it came from, in one message.

    """
    messages = unknown_given(node, given, declared, sources, others)
    if messages:
        raise ConfigError('; '.join(messages))
