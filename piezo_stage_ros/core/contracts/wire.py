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
The wire contract of a stage: topics, message types, joint name, stamps and diagnostics.

One module says what goes over the wire and into a bag; the nodes, the launch file, the bag
writer and the bag reader take it from here (rclpy- and rosbags-free, so it lives in ``core``:
the offline loop reads the controller's diagnostics with the same reader as the nodes). The
bytes themselves are :mod:`piezo_stage_ros.core.contracts.cdr`.

Topics, relative to the launch namespace (several stages side by side), all under the stage
prefix ``stage/``; under the root namespace the bag of a run has them as ``/stage/position`` ...
(:data:`DEFAULT_NAMESPACE`, the bag's *namespace* is everything before the last ``/``):

- ``stage/position``, ``sensor_msgs/msg/JointState``: stamp t_k, name ['stage'], position [y_k] m;
- ``stage/reference``, ``sensor_msgs/msg/JointState``: stamp t_k, name ['stage'],
  position [x_d] m, velocity [x_d'] m/s;
- ``stage/command``, ``std_msgs/msg/Float64``: amplifier input u_k [V], held over the sample
  (no stamp);
- ``stage/diagnostics``, ``sensor_msgs/msg/JointState``: stamp t_k, name [keys],
  position [values]: the controller's internals, keys in sorted order
  (:func:`diagnostic_reader`);
- ``stage/true_position``, ``sensor_msgs/msg/JointState``: stamp t_k, name ['stage'],
  position [x(t_k)] m, the true position behind y_k (no noise, no ADC): simulation only, written
  by the offline runner's bags (:data:`SIMULATION_TOPICS`; no node publishes it);
- ``stage/block``, ``std_msgs/msg/Float64MultiArray``: many samples per message (the recording
  path that keeps every sample under load, about 100 messages a second; layout below);
- ``stage/status``, ``diagnostic_msgs/msg/DiagnosticStatus``: plant counters, about once a second;
- ``stage/trajectory``, ``std_msgs/msg/String``: a new trajectory and the stamp of its t = 0,
  from the trajectory node at each switch, for a controller that predicts from its own copy
  (JSON, :func:`piezo_stage_ros.nodes.logic.announce_trajectory`);
- ``/clock``, ``rosgraph_msgs/msg/Clock``: t_k, lockstep only (absolute: one clock per graph).

Stamps are ``builtin_interfaces/msg/Time`` (int32 sec, uint32 nanosec) of the sample time;
:func:`ns_to_stamp` and :func:`stamp_to_ns` convert, in integer nanoseconds.

The block layout (``stage/block``; :func:`block_columns`, :func:`parse_block_columns`): a
row-major matrix of n samples (rows) by c columns (``data[i * c + j]``), described by the
message's own ``layout`` as the MultiArrayLayout convention has it: ``dim[0]`` = {label
:data:`BLOCK_ROWS_LABEL`, size n, stride n * c}, ``dim[1]`` = {label: the column names joined
by :data:`BLOCK_SEPARATOR`, size c, stride c}, ``data_offset`` 0. The columns, in this order:

- :data:`BLOCK_COLUMNS`, always: ``sample`` (the number of the sample among those the loop
  served: 0, 1, 2 ... without gaps, so a gap is a sample lost on its way to the bag),
  ``stamp_sec`` and ``stamp_nanosec`` (t_k as in a header stamp: both integers, exact in
  float64), ``position_m`` (y_k), ``reference_m`` (x_d), ``velocity_mps`` (x_d'),
  ``command_v`` (u_k as the controller computed it);
- :data:`BLOCK_OPTIONAL` where the writer knows them: ``applied_v`` (the amplifier input the
  plant held over [t_k, t_k+1), as ``stage/applied`` carries it; NaN until known),
  ``true_position_m`` (x(t_k), a simulated stage only);
- the controller's diagnostics, each named :data:`BLOCK_DIAGNOSTIC_PREFIX` + key, keys sorted;
  NaN in the rows of samples without diagnostics.

A message carries one column set; when the diagnostic keys change (a controller rebuilt of
another kind) the writer starts a new message. Rows are in sample order.

A stage of several axes (:func:`axis_joint_names`) keeps one message per sample and topic, all
axes in it, so that a sample stays atomic (one stamp, one message to wait for in lockstep, one
row of a bag): ``stage/position``, ``stage/reference`` and ``stage/true_position`` carry one
joint per axis, named ``stage_<axis>`` in the stage's axis order, each array one entry per
joint; ``stage/command`` is a ``std_msgs/msg/Float64MultiArray`` (:data:`AXES_COMMAND_TYPE`)
with ``data`` in the axis order and ``layout.dim`` = [{label :data:`AXES_LABEL`, size N,
stride N}] (:func:`axes_command_dims`), the convention of ros2_control's joint-group
controllers; its other type makes a one-axis subscriber refuse it instead of reading one axis.
The diagnostics carry every axis' keys as ``<axis>.<key>``.

The block of a stage of several axes (:func:`axes_block_columns`) keeps one row a sample for
all axes: ``sample``, ``stamp_sec``, ``stamp_nanosec`` once, then for each axis in the stage's
order its own columns named ``<axis>.<column>`` (``position_m``, ``reference_m``,
``velocity_mps``, ``command_v``, then ``applied_v`` and ``true_position_m`` where the writer
knows them), then the diagnostics as ``diagnostics.<axis>.<key>``, keys sorted. The axes'
columns are told from a one-axis block's by the separator in their name; a reader of one axis
refuses such a block by name instead of reading one axis.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
import math
import operator
import re
from typing import Final, NamedTuple

from piezo_stage_ros.core.contracts.errors import BagError
from piezo_stage_ros.core.contracts.interfaces import Controller

__all__ = [
    'APPLIED', 'BAG_TOPICS', 'BLOCK', 'BLOCK_COLUMNS', 'BLOCK_DIAGNOSTIC_PREFIX',
    'BLOCK_OPTIONAL', 'BLOCK_RECORDED_TOPICS', 'BLOCK_ROWS_LABEL', 'BLOCK_SAMPLES',
    'BLOCK_SEPARATOR', 'BLOCK_TYPE', 'CLOCK', 'CLOCK_TYPE', 'COMMAND', 'COMMAND_TYPE',
    'DEFAULT_NAMESPACE', 'DIAGNOSTICS', 'JOINT_NAME', 'JOINT_STATE_TYPE', 'META_KEY', 'NS_PER_S',
    'POSITION', 'RECORDED_TOPICS', 'REFERENCE', 'REQUIRED_TOPICS', 'SIMULATION_TOPICS', 'STAGE',
    'STATUS', 'STATUS_TYPE', 'STORAGE_IDS', 'TOPIC_TYPES', 'TRAJECTORY', 'TRAJECTORY_TYPE',
    'TRUE_POSITION', 'BlockColumns',
    'AXES_BAG_TOPICS', 'AXES_BLOCK_OWN', 'AXES_BLOCK_SHARED', 'AXES_COMMAND_TYPE', 'AXES_LABEL',
    'AXIS_DIAGNOSTIC_SEPARATOR',
    'AXIS_JOINT_PREFIX', 'axes_command_dims', 'axis_joint_names', 'axis_of_joint',
    'AxesBlockColumns', 'axes_block_columns', 'block_columns', 'block_topic',
    'diagnostic_reader', 'is_axes_block', 'normalize_namespace', 'ns_to_stamp',
    'parse_axes_block_columns', 'parse_block_columns', 'stamp_to_ns', 'topic_names',
]

JOINT_STATE_TYPE: Final = 'sensor_msgs/msg/JointState'
COMMAND_TYPE: Final = 'std_msgs/msg/Float64'
CLOCK_TYPE: Final = 'rosgraph_msgs/msg/Clock'
STATUS_TYPE: Final = 'diagnostic_msgs/msg/DiagnosticStatus'
BLOCK_TYPE: Final = 'std_msgs/msg/Float64MultiArray'
TRAJECTORY_TYPE: Final = 'std_msgs/msg/String'

#: The stage's topic prefix, and the name of its one joint in every JointState.
STAGE: Final = 'stage'
JOINT_NAME: Final = STAGE

#: The topics of a run in a bag: the last part of the name -> message type, in the order the
#: nodes publish a sample (``diagnostics``, ``applied`` and ``true_position`` are optional, the
#: others required).
BAG_TOPICS: Final[Mapping[str, str]] = {
    'position': JOINT_STATE_TYPE,
    'reference': JOINT_STATE_TYPE,
    'command': COMMAND_TYPE,
    'diagnostics': JOINT_STATE_TYPE,
    'applied': JOINT_STATE_TYPE,
    'true_position': JOINT_STATE_TYPE,
}
REQUIRED_TOPICS: Final = ('position', 'reference', 'command')
#: The command of a stage of several axes: all axes' inputs of one sample in one message.
AXES_COMMAND_TYPE: Final = 'std_msgs/msg/Float64MultiArray'
#: ``layout.dim[0].label`` of a multi-axis command.
AXES_LABEL: Final = 'axes'
#: Joint name of axis ``a`` of a stage of several axes: ``stage_a``.
AXIS_JOINT_PREFIX: Final = STAGE + '_'
#: Joins an axis and a diagnostic key in the diagnostics of a stage of several axes.
AXIS_DIAGNOSTIC_SEPARATOR: Final = '.'
#: :data:`BAG_TOPICS` of a stage of several axes: the command is one array a sample.
AXES_BAG_TOPICS: Final[Mapping[str, str]] = {
    key: AXES_COMMAND_TYPE if key == 'command' else msgtype
    for key, msgtype in BAG_TOPICS.items()}
#: Bag topics only a simulation knows (the offline runner writes them; no node publishes them).
SIMULATION_TOPICS: Final = ('true_position',)
#: The rosbag2 storage plugins a run's bag can be written in (the first is the default).
STORAGE_IDS: Final = ('mcap', 'sqlite3')

POSITION: Final = f'{STAGE}/position'
REFERENCE: Final = f'{STAGE}/reference'
COMMAND: Final = f'{STAGE}/command'
DIAGNOSTICS: Final = f'{STAGE}/diagnostics'
#: Real time: stamp t_k, name ['stage'], effort [the amplifier input the plant held over
#: [t_k, t_k+1)] in V (what it applied, whatever command came), published after t_k+1.
APPLIED: Final = f'{STAGE}/applied'
#: Simulation only: stamp t_k, name ['stage'], position [x(t_k)], the true position behind y_k.
TRUE_POSITION: Final = f'{STAGE}/true_position'
#: Plant counters (late samples, resends, watchdog trips, bridge losses), about once a second.
STATUS: Final = f'{STAGE}/status'
#: A new trajectory and the stamp of its t = 0, at each switch of the trajectory node.
TRAJECTORY: Final = f'{STAGE}/trajectory'
CLOCK: Final = '/clock'
#: Many samples per message (``std_msgs/msg/Float64MultiArray``, the block layout above).
BLOCK: Final = f'{STAGE}/block'

#: Topic name as the nodes use it (relative, except ``/clock``) -> message type.
TOPIC_TYPES: Final[Mapping[str, str]] = {
    **{f'{STAGE}/{leaf}': msgtype for leaf, msgtype in BAG_TOPICS.items()},
    BLOCK: BLOCK_TYPE,
    STATUS: STATUS_TYPE,
    CLOCK: CLOCK_TYPE,
}
#: What ``ros2 bag record`` takes from a stage (relative to the launch namespace): what the
#: nodes publish, so not the :data:`SIMULATION_TOPICS`.
RECORDED_TOPICS: Final = (POSITION, REFERENCE, COMMAND, DIAGNOSTICS, APPLIED, BLOCK, STATUS)
#: What the recorder takes from a real-time loop that publishes :data:`BLOCK`: every sample is
#: in the blocks, so the per-sample topics (10 000 messages a second each, for live use) are
#: left to live subscribers.
BLOCK_RECORDED_TOPICS: Final = (BLOCK, STATUS)

#: Rows of a block the nodes publish: 10 ms at 10 kHz, about 100 messages a second.
BLOCK_SAMPLES: Final = 100
#: ``dim[0].label`` of a block.
BLOCK_ROWS_LABEL: Final = 'samples'
#: Joins the column names in ``dim[1].label``.
BLOCK_SEPARATOR: Final = ','
#: The columns of every block, first and in this order.
BLOCK_COLUMNS: Final = ('sample', 'stamp_sec', 'stamp_nanosec', 'position_m', 'reference_m',
                        'velocity_mps', 'command_v')
#: Columns a block has where its writer knows them, after :data:`BLOCK_COLUMNS`, in this order.
BLOCK_OPTIONAL: Final = ('applied_v', 'true_position_m')
#: Prefix of a diagnostic's column name (the diagnostics come last).
BLOCK_DIAGNOSTIC_PREFIX: Final = 'diagnostics.'

#: The bag namespace of a stage launched in the root namespace.
DEFAULT_NAMESPACE: Final = '/' + STAGE
#: Key of the run description (JSON) in a bag's ``custom_data``.
META_KEY: Final = 'piezo_stage_ros.meta'

NS_PER_S: Final = 1_000_000_000

_NAMESPACE_RE = re.compile(r'^(/[A-Za-z][A-Za-z0-9_]*)*$')


def ns_to_stamp(stamp_ns: int) -> tuple[int, int]:
    """Return ``(sec, nanosec)`` of a ``builtin_interfaces/Time`` for ``stamp_ns`` [ns] >= 0."""
    return divmod(int(stamp_ns), NS_PER_S)


def stamp_to_ns(sec: int, nanosec: int) -> int:
    """Return the nanoseconds of a ``builtin_interfaces/Time`` (``sec`` [s], ``nanosec`` [ns])."""
    return int(sec) * NS_PER_S + int(nanosec)


def normalize_namespace(namespace: str) -> str:
    """
    Return a bag namespace in absolute form without a trailing ``/`` (``''`` for the root).

    Parameters
    ----------
    namespace : str
        ROS namespace, e.g. ``'/stage'``, ``'stage'``, ``'/'``.

    Raises
    ------
    BagError
        If it is not a valid ROS namespace.

    """
    ns = namespace.rstrip('/')
    if ns and not ns.startswith('/'):
        ns = '/' + ns
    if not _NAMESPACE_RE.match(ns):
        raise BagError(
            f'namespace {namespace!r} is not a valid ROS namespace; allowed: '
            "'/name[/name...]' of letters, digits and '_' (each part starting with a letter)")
    return ns


def topic_names(namespace: str = DEFAULT_NAMESPACE) -> dict[str, str]:
    """
    Return the absolute topic names of a run under a namespace.

    Parameters
    ----------
    namespace : str
        ROS namespace, e.g. ``'/stage'`` (``''`` or ``'/'`` for the root).

    Returns
    -------
    dict of str to str
        ``{'position': '/stage/position', 'reference': ..., 'command': ..., 'diagnostics': ...}``.

    """
    ns = normalize_namespace(namespace)
    return {key: f'{ns}/{key}' for key in BAG_TOPICS}


def block_topic(namespace: str = DEFAULT_NAMESPACE) -> str:
    """Return the absolute name of the block topic under a namespace (``'/stage/block'``)."""
    return f'{normalize_namespace(namespace)}/{BLOCK.rsplit("/", 1)[1]}'


def axis_joint_names(axes: Sequence[str]) -> tuple[str, ...]:
    """
    Return the joint names of a stage of several axes, in its axis order (``stage_x`` ...).

    Raises
    ------
    BagError
        An axis name that is empty, holds white space or :data:`AXIS_DIAGNOSTIC_SEPARATOR`, or
        appears twice.

    """
    names = tuple(str(a) for a in axes)
    if not names or len(set(names)) != len(names) or any(
            not a or AXIS_DIAGNOSTIC_SEPARATOR in a or any(c.isspace() for c in a)
            for a in names):
        raise BagError(f'axis names {list(names)}: allowed: one or more distinct names without '
                       f'{AXIS_DIAGNOSTIC_SEPARATOR!r} or white space')
    return tuple(AXIS_JOINT_PREFIX + a for a in names)


def axis_of_joint(joint: str) -> str:
    """
    Return the axis a joint name of a stage of several axes stands for (``stage_x`` -> ``x``).

    Raises
    ------
    BagError
        A name that does not start with :data:`AXIS_JOINT_PREFIX` or has nothing after it.

    """
    if not joint.startswith(AXIS_JOINT_PREFIX) or len(joint) == len(AXIS_JOINT_PREFIX):
        raise BagError(f'joint {joint!r} is not an axis of a stage; allowed: '
                       f"'{AXIS_JOINT_PREFIX}<axis>'")
    return joint[len(AXIS_JOINT_PREFIX):]


def axes_command_dims(n: int) -> list[tuple[str, int, int]]:
    """Return ``layout.dim`` of a multi-axis command of ``n`` axes: [(``'axes'``, n, n)]."""
    return [(AXES_LABEL, int(n), int(n))]


def block_columns(*, applied: bool = False, true_position: bool = False,
                  diagnostics: Sequence[str] = ()) -> tuple[str, ...]:
    """
    Return the column names of a block, in wire order.

    Parameters
    ----------
    applied : bool
        Whether the block carries ``applied_v`` (a real-time loop).
    true_position : bool
        Whether it carries ``true_position_m`` (a simulated stage).
    diagnostics : sequence of str
        The controller's diagnostic keys (sorted here).

    Raises
    ------
    BagError
        A diagnostic key that is empty or holds :data:`BLOCK_SEPARATOR` or white space.

    """
    optional = tuple(name for name, on in zip(BLOCK_OPTIONAL, (applied, true_position)) if on)
    return BLOCK_COLUMNS + optional + _diagnostic_columns(diagnostics)


def _diagnostic_columns(diagnostics: Sequence[str]) -> tuple[str, ...]:
    """Return the diagnostics' column names, keys sorted; refuse a key no column can carry."""
    keys = sorted(str(k) for k in diagnostics)
    if len(set(keys)) != len(keys):
        raise BagError(f'diagnostic keys {keys} name a column twice')
    for key in keys:
        if not key or BLOCK_SEPARATOR in key or any(c.isspace() for c in key):
            raise BagError(f'diagnostic key {key!r} cannot name a block column; allowed: a '
                           f'non-empty name without {BLOCK_SEPARATOR!r} or white space')
    return tuple(BLOCK_DIAGNOSTIC_PREFIX + k for k in keys)


#: The columns of a block of several axes that every sample shares, first and in this order.
AXES_BLOCK_SHARED: Final = BLOCK_COLUMNS[:3]
#: Each axis' own columns in a block of several axes, as ``<axis>.<column>``, in this order.
AXES_BLOCK_OWN: Final = BLOCK_COLUMNS[3:]


def axes_block_columns(axes: Sequence[str], *, applied: bool = False,
                       true_position: bool = False,
                       diagnostics: Sequence[str] = ()) -> tuple[str, ...]:
    """
    Return the column names of a block of several axes, in wire order (see the module).

    Parameters
    ----------
    axes : sequence of str
        The axes, in the stage's order.
    applied, true_position : bool
        Whether every axis carries ``applied_v`` / ``true_position_m``.
    diagnostics : sequence of str
        The diagnostic keys, ``<axis>.<key>`` (sorted here).

    Raises
    ------
    BagError
        An axis name :func:`axis_joint_names` refuses or holding :data:`BLOCK_SEPARATOR`; a
        diagnostic key as :func:`block_columns` refuses it.

    """
    names = tuple(str(a) for a in axes)
    axis_joint_names(names)
    if any(BLOCK_SEPARATOR in a for a in names):
        raise BagError(f'axis names {list(names)} cannot name block columns; allowed: names '
                       f'without {BLOCK_SEPARATOR!r}')
    optional = tuple(name for name, on in zip(BLOCK_OPTIONAL, (applied, true_position)) if on)
    own = tuple(f'{a}{AXIS_DIAGNOSTIC_SEPARATOR}{column}' for a in names
                for column in AXES_BLOCK_OWN + optional)
    return AXES_BLOCK_SHARED + own + _diagnostic_columns(diagnostics)


class BlockColumns(NamedTuple):
    """
    Where the columns of a block are (:func:`parse_block_columns`).

    Attributes
    ----------
    names : tuple of str
        All column names, in order.
    applied, true_position : int
        Index of ``applied_v`` / ``true_position_m``, -1 when the block has none.
    diagnostics : tuple of str
        The diagnostic keys (without the prefix), in column order.
    first_diagnostic : int
        Index of the first diagnostic column.

    """

    names: tuple[str, ...]
    applied: int
    true_position: int
    diagnostics: tuple[str, ...]
    first_diagnostic: int


def parse_block_columns(label: str) -> BlockColumns:
    """
    Return the column set a block's ``dim[1].label`` names.

    Raises
    ------
    BagError
        When the label does not start with :data:`BLOCK_COLUMNS`, or has an unknown column,
        a column twice, or a column out of the order of :func:`block_columns`.

    """
    if is_axes_block(label):
        raise BagError(f'block columns {label!r}: a block of several axes; allowed here: the '
                       'block of one axis (a run of several axes is read as such: read_axes)')
    names = tuple(label.split(BLOCK_SEPARATOR)) if label else ()
    fixed = len(BLOCK_COLUMNS)
    if names[:fixed] != BLOCK_COLUMNS:
        raise BagError(f'block columns {label!r} do not start with '
                       f'{BLOCK_SEPARATOR.join(BLOCK_COLUMNS)!r}')
    rest = names[fixed:]
    optional = tuple(n for n in rest if not n.startswith(BLOCK_DIAGNOSTIC_PREFIX))
    keys = tuple(n[len(BLOCK_DIAGNOSTIC_PREFIX):] for n in rest
                 if n.startswith(BLOCK_DIAGNOSTIC_PREFIX))
    try:
        expected = block_columns(applied='applied_v' in optional,
                                 true_position='true_position_m' in optional, diagnostics=keys)
    except BagError as err:
        raise BagError(f'block columns {label!r}: {err}') from None
    if names != expected:
        raise BagError(f'block columns {label!r}: expected {BLOCK_SEPARATOR.join(expected)!r}')
    index = {name: i for i, name in enumerate(names)}
    return BlockColumns(names, index.get('applied_v', -1), index.get('true_position_m', -1),
                        keys, fixed + len(optional))


def is_axes_block(label: str) -> bool:
    """Return whether a block's ``dim[1].label`` names the columns of several axes."""
    names = label.split(BLOCK_SEPARATOR)
    shared = len(AXES_BLOCK_SHARED)
    return len(names) > shared and AXIS_DIAGNOSTIC_SEPARATOR in names[shared]


class AxesBlockColumns(NamedTuple):
    """
    Where the columns of a block of several axes are (:func:`parse_axes_block_columns`).

    Attributes
    ----------
    names : tuple of str
        All column names, in order.
    axes : tuple of str
        The axes, in the stage's order.
    applied, true_position : bool
        Whether the axes carry ``applied_v`` / ``true_position_m``.
    diagnostics : tuple of str
        The diagnostic keys (``<axis>.<key>``, without the prefix), in column order.

    """

    names: tuple[str, ...]
    axes: tuple[str, ...]
    applied: bool
    true_position: bool
    diagnostics: tuple[str, ...]

    def column(self, axis: str, name: str) -> int:
        """Return the index of axis ``axis``' column ``name`` (``position_m`` ...)."""
        return self.names.index(f'{axis}{AXIS_DIAGNOSTIC_SEPARATOR}{name}')


def parse_axes_block_columns(label: str) -> AxesBlockColumns:
    """
    Return the column set of a block of several axes from its ``dim[1].label``.

    Raises
    ------
    BagError
        When the label is not what :func:`axes_block_columns` writes for some axes: the shared
        columns first, every axis with the same columns in order, the diagnostics last.

    """
    names = tuple(label.split(BLOCK_SEPARATOR)) if label else ()
    shared = len(AXES_BLOCK_SHARED)
    if names[:shared] != AXES_BLOCK_SHARED:
        raise BagError(f'block columns {label!r} do not start with '
                       f'{BLOCK_SEPARATOR.join(AXES_BLOCK_SHARED)!r}')
    own = [n for n in names[shared:] if not n.startswith(BLOCK_DIAGNOSTIC_PREFIX)]
    axes = tuple(dict.fromkeys(n.split(AXIS_DIAGNOSTIC_SEPARATOR, 1)[0] for n in own))
    keys = tuple(n[len(BLOCK_DIAGNOSTIC_PREFIX):] for n in names[shared:]
                 if n.startswith(BLOCK_DIAGNOSTIC_PREFIX))
    first = f'{axes[0]}{AXIS_DIAGNOSTIC_SEPARATOR}' if axes else ''
    try:
        expected = axes_block_columns(axes, applied=first + 'applied_v' in own,
                                      true_position=first + 'true_position_m' in own,
                                      diagnostics=keys)
    except BagError as err:
        raise BagError(f'block columns {label!r}: {err}') from None
    if names != expected:
        raise BagError(f'block columns {label!r}: expected {BLOCK_SEPARATOR.join(expected)!r}')
    return AxesBlockColumns(names, axes, first + 'applied_v' in own,
                            first + 'true_position_m' in own, keys)


def diagnostic_reader(controller: Controller
                      ) -> tuple[tuple[str, ...], Callable[[], Sequence[float]]]:
    """
    Return a controller's diagnostic names in wire order and a function reading their values.

    The wire order is the sorted order of the names, whichever way the controller offers them:
    the cheap pair ``diagnostic_names`` (a tuple of str) / ``diagnostic_values()`` (floats in
    that order), or else its ``diagnostics()`` mapping. Sorted, because bags have always stored
    the keys sorted, and because then a controller's layout does not depend on the order in
    which it happens to build its mapping: the offline loop, the controller node and a bag all
    carry the same columns in the same order.

    Parameters
    ----------
    controller : Controller
        The controller whose internals are read.

    Returns
    -------
    names : tuple of str
        Diagnostic names, sorted.
    read : callable
        ``read()`` returns the current values in the order of ``names``; a name the mapping
        no longer has reads as NaN.

    """
    names = getattr(controller, 'diagnostic_names', None)
    values = getattr(controller, 'diagnostic_values', None)
    if isinstance(names, tuple) and callable(values):
        declared = tuple(str(n) for n in names)
        order = sorted(range(len(declared)), key=declared.__getitem__)
        keys = tuple(declared[i] for i in order)
        if order == list(range(len(order))):
            return keys, values
        if len(order) == 1:  # itemgetter of one index returns the item, not a tuple
            return keys, lambda: (values()[0],)
        pick = operator.itemgetter(*order)
        return keys, lambda: pick(values())  # type: ignore[no-any-return]
    keys = tuple(sorted(controller.diagnostics()))
    diagnostics = controller.diagnostics

    def read() -> Sequence[float]:
        d = diagnostics()
        try:
            return [float(d[k]) for k in keys]
        except KeyError:  # a controller whose diagnostics change shape: NaN for the missing
            return [float(d.get(k, math.nan)) for k in keys]
    return keys, read
