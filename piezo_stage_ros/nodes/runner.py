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
Running one or several node classes in one process, on one executor (imports rclpy).

Every executable of the package goes through :func:`run`: it initialises rclpy with the ROS
arguments, builds the nodes (a bad parameter, or one given that the node does not declare,
prints one line and exits 2), configures and activates the managed ones (a refused transition
prints its reason and exits 2; ``--autostart false`` leaves them unconfigured for a lifecycle
manager), spins them on one ``rclpy.experimental.EventsExecutor`` (or the
single-threaded executor on request) until
Ctrl-C, an external shutdown, or the plant's run is complete, and always destroys the nodes (the
plant drives its safe voltage there) and shuts rclpy down.
"""

from __future__ import annotations

import argparse
import functools
import sys
from typing import Any, Callable, Protocol, Sequence, TypeVar

from piezo_stage_ros.core.contracts.cdr import CdrError
from piezo_stage_ros.core.contracts.errors import PiezoStageError
from piezo_stage_ros.nodes.parameters import check_undeclared, multi_axis_hint
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.task import Future
from rclpy.utilities import remove_ros_args

__all__ = ['decode_or_drop', 'make_executor', 'run', 'start_managed', 'stops_quietly']

NodeFactory = Callable[[], Node]
_Message = TypeVar('_Message')


class _CountsMalformed(Protocol):
    malformed: int

    def get_logger(self) -> Any: ...


def stops_quietly(callback: Callable[[Any, bytes], None]) -> Callable[[Any, bytes], None]:
    """
    Wrap a node's subscription callback so that Ctrl-C inside it ends it without a trace.

    rclpy shuts down on the interrupt and :func:`run` stops cleanly; a traceback out of the
    executor would only hide that.

    Parameters
    ----------
    callback : callable
        A node's method taking the serialized message.

    Returns
    -------
    callable

    """
    @functools.wraps(callback)
    def guarded(node: Any, data: bytes) -> None:
        try:
            callback(node, data)
        except KeyboardInterrupt:
            return
    return guarded


def decode_or_drop(node: _CountsMalformed, topic: str, decode: Callable[[bytes], _Message],
                   data: bytes) -> _Message | None:
    """
    Return ``decode(data)``, or None for a malformed message, counted and dropped.

    One bad publisher must neither stop a node's loop nor flood its log: the message is
    counted in ``node.malformed`` and warned about at most once a second.

    Parameters
    ----------
    node : Node
        The receiving node, with a ``malformed`` counter.
    topic : str
        The topic, for the warning.
    decode : callable
        The message's decoder (raises ``CdrError``).
    data : bytes
        The serialized message.

    Returns
    -------
    object or None

    """
    try:
        return decode(data)
    except CdrError as exc:
        node.malformed += 1
        node.get_logger().warning(f'{topic}: {exc}; dropped', throttle_duration_sec=1.0)
        return None


def make_executor(kind: str = 'events', context: rclpy.context.Context | None = None
                  ) -> rclpy.executors.Executor:
    """
    Return the executor ``kind`` names.

    Parameters
    ----------
    kind : str
        ``'events'`` (``rclpy.experimental.EventsExecutor``, the fastest in Jazzy) or
        ``'single'`` (``SingleThreadedExecutor``).
    context : rclpy.context.Context, optional
        Context of the executor; default the global one.

    """
    if kind == 'events':
        try:
            from rclpy.experimental import EventsExecutor
        except ImportError:
            # rclpy before 7.1.4 (Jazzy's first year) has no EventsExecutor: run, and say so
            print('rclpy.experimental.EventsExecutor is missing (rclpy >= 7.1.4 has it): '
                  'using SingleThreadedExecutor, several times slower per sample; update '
                  'ROS 2 Jazzy or pass --executor single', file=sys.stderr)
        else:
            return EventsExecutor(context=context)
    return SingleThreadedExecutor(context=context)


def start_managed(nodes: Sequence[Node]) -> None:
    """
    Configure and activate every managed node of ``nodes``, in order.

    Raises
    ------
    PiezoStageError
        With the node's reason when a transition fails (the node logged it too).

    """
    for node in nodes:
        if not isinstance(node, LifecycleNode):
            continue
        for name, trigger in (('configure', node.trigger_configure),
                              ('activate', node.trigger_activate)):
            if trigger() != TransitionCallbackReturn.SUCCESS:
                raise PiezoStageError(f'{node.get_name()}: {name} failed: '
                                      f'{getattr(node, "refused", "")}')


def run(prog: str, factories: Sequence[tuple[str, NodeFactory]],
        argv: Sequence[str] | None = None, description: str = '',
        connect: Callable[..., None] | None = None) -> int:
    """
    Run node classes in this process until shutdown or the end of the plant's run.

    Parameters
    ----------
    prog : str
        Executable name (for messages).
    factories : sequence of (str, callable)
        ``(short name, factory)``; ``--nodes`` picks some of them by short name.
    argv : sequence of str, optional
        Command line including ROS arguments (default ``sys.argv``).
    description : str
        Help text.
    connect : callable, optional
        ``connect(*nodes)`` for ``--direct``: wires the nodes to call each other (needs every
        node of ``factories`` in this process).

    Returns
    -------
    int
        0 on a normal end, 1 after a fault in a callback, 2 on bad parameters.

    """
    args = list(sys.argv if argv is None else argv)
    parser = argparse.ArgumentParser(prog=prog, description=description)
    names = [name for name, _ in factories]
    parser.add_argument('--nodes', default=','.join(names),
                        help=f'comma-separated subset of {",".join(names)} to run here')
    parser.add_argument('--executor', choices=('events', 'single'), default='events',
                        help='EventsExecutor (default) or SingleThreadedExecutor')
    parser.add_argument('--autostart', choices=('true', 'false'), default='true',
                        help='configure and activate the managed nodes at once (default); '
                             'false: leave them unconfigured (ros2 lifecycle set)')
    if connect is not None:
        parser.add_argument('--direct', action='store_true',
                            help='hand each sample from node to node by call (intra-process); '
                                 'the topics are published for outside subscribers only')
    try:
        own = remove_ros_args(args)
    except RuntimeError as exc:  # rclpy's UnknownROSArgsError is one
        print(f'{prog}: ROS arguments refused: {exc}{multi_axis_hint(args)}', file=sys.stderr)
        return 2
    opts = parser.parse_args(own[1:])
    chosen = [n.strip() for n in opts.nodes.split(',') if n.strip()]
    unknown = [n for n in chosen if n not in names]
    direct = bool(getattr(opts, 'direct', False))
    if direct and sorted(chosen) != sorted(names):
        print(f'{prog}: --direct needs every node in this process ({", ".join(names)})',
              file=sys.stderr)
        return 2
    if unknown or not chosen:
        print(f'{prog}: --nodes {opts.nodes!r}: choose among {", ".join(names)}',
              file=sys.stderr)
        return 2
    try:
        rclpy.init(args=args)
    except RuntimeError as exc:
        print(f'{prog}: ROS arguments refused: {exc}{multi_axis_hint(args)}', file=sys.stderr)
        return 2
    nodes: list[Node] = []
    try:
        for name, factory in factories:
            if name in chosen:
                # a managed node is made unconfigured: its transitions come after the wiring
                managed = isinstance(factory, type) and issubclass(factory, LifecycleNode)
                made: Any = factory(autostart=False) if managed else factory()  # type: ignore
                nodes.append(made)
        # ROS drops a given parameter no node declares: refuse it before any loop starts
        check_undeclared(nodes, args)
        if direct and connect is not None:
            connect(*nodes)
        if opts.autostart == 'true':
            start_managed(nodes)
    except (PiezoStageError, ParameterException) as exc:
        text = str(exc)  # a node's own message may start with its name, the program's
        print(text if text.startswith(f'{prog}: ') else f'{prog}: {text}', file=sys.stderr)
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
        return 2
    except KeyboardInterrupt:
        # Ctrl-C (or the launch's SIGINT) while a node was still being built
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
        return 0
    executor = make_executor(opts.executor)
    for node in nodes:
        executor.add_node(node)
    finished: Future | None = next((getattr(n, 'finished', None) for n in nodes
                                    if getattr(n, 'finished', None) is not None), None)
    code = 0
    try:
        if finished is not None:
            executor.spin_until_future_complete(finished)
            if finished.done() and finished.exception() is not None:
                print(f'{prog}: {finished.exception()}', file=sys.stderr)
                code = 1
        else:
            executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if rclpy.ok():
            raise
        # a signal shut the context down while a callback ran: an ordinary stop
    finally:
        for node in nodes:
            # destroy_node drives the plant's safe voltage: it must run for every node
            try:
                executor.remove_node(node)
            finally:
                node.destroy_node()
        executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown()
    return code
