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
What every command-line program shares: parser, exit status, configuration, progress.

- :class:`Parser`: an ``argparse`` parser whose usage errors raise :class:`UsageError` instead of
  exiting, so that :func:`run_command` reports them in one line;
- :func:`run_command`: parse, run, and map errors to the documented exit status: 0 success,
  1 a bad parameter, configuration, file or refused run (:class:`PiezoStageError`,
  ``OSError``), 2 bad command-line usage, 130 interrupted; the error is one line on stderr,
  ``PROG: error: ...``; :func:`command_main` makes a command's ``main(argv)`` of it;
- :func:`choices`: the allowed strings of a declared parameter, for ``choices=`` (a command
  never retypes them);
- :func:`add_config_options` and :func:`read_config`: ``--config FILE`` on top of
  ``config/default.yaml`` and ``--param NODE:NAME=VALUE``, and :func:`loop_overrides`, the short
  flags (``--plant``, ``--controller``, ``--trajectory`` ...) as parameter values; the objects
  come from :class:`piezo_stage_ros.core.config.loader.LoopConfig`, as everywhere else;
- :class:`Progress`: one progress display on stderr (elapsed-time lines, or a percentage that
  rewrites itself on a terminal).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import sys
import time
from typing import Any, Callable, NoReturn, Protocol, Sequence, TextIO

from piezo_stage_ros.core.config.loader import Config, find_config, load_config, LoopConfig
from piezo_stage_ros.core.contracts.errors import ConfigError, ParameterError, PiezoStageError
from piezo_stage_ros.core.contracts.params import Params, ParamSpec
import yaml

__all__ = ['Main', 'Parser', 'Progress', 'UsageError', 'add_config_options', 'choices',
           'command_main', 'error', 'loop_overrides', 'note', 'offline_loop', 'parse_param',
           'read_config', 'run_command']


class UsageError(Exception):
    """Bad command-line usage (exit status 2)."""


class Parser(argparse.ArgumentParser):
    """An argument parser that raises :class:`UsageError` instead of printing and exiting."""

    def error(self, message: str) -> NoReturn:
        raise UsageError(message)


def error(prog: str, message: str) -> None:
    """Print ``PROG: error: message`` on stderr."""
    print(f'{prog}: error: {message}', file=sys.stderr, flush=True)


def note(prog: str, message: str) -> None:
    """Print ``PROG: note: message`` on stderr."""
    print(f'{prog}: note: {message}', file=sys.stderr, flush=True)


def run_command(prog: str, parser: argparse.ArgumentParser,
                body: Callable[[argparse.Namespace], int],
                argv: Sequence[str] | None = None) -> int:
    """
    Parse the command line, run ``body`` and map what it raises to an exit status.

    Parameters
    ----------
    prog : str
        Program name, for messages.
    parser : argparse.ArgumentParser
        Usually a :class:`Parser` (``--help`` still prints and exits 0).
    body : callable
        ``body(args)`` returns the exit status of a normal end.
    argv : sequence of str, optional
        Arguments without the program name; default ``sys.argv[1:]``.

    Returns
    -------
    int
        ``body``'s status; 1 for :class:`PiezoStageError` or ``OSError``; 2 for
        :class:`UsageError` (from parsing or from ``body``); 130 on Ctrl-C.

    """
    try:
        args = parser.parse_args(argv)
        return body(args)
    except UsageError as exc:
        error(prog, f'{exc} (see {prog} --help)')
        return 2
    except PiezoStageError as exc:
        error(prog, str(exc))
        return 1
    except OSError as exc:
        where = f'{exc.filename}: ' if exc.filename else ''
        error(prog, where + (exc.strerror or str(exc)))
        return 1
    except KeyboardInterrupt:
        error(prog, 'interrupted')
        return 130


class Main(Protocol):
    """The entry point of a command: ``main(argv)`` returns the exit status."""

    def __call__(self, argv: Sequence[str] | None = None) -> int: ...


def command_main(prog: str, build_parser: Callable[[], argparse.ArgumentParser],
                 body: Callable[[argparse.Namespace], int], statuses: str, *,
                 keep_argv: bool = False) -> Main:
    """
    Return the ``main(argv)`` of a command: :func:`run_command` on its parser and body.

    Every console script's entry point is this one function, so that parsing, the exit
    statuses and the error lines cannot drift apart between commands.

    Parameters
    ----------
    prog : str
        Program name, for messages and the docstring.
    build_parser : callable
        Returns the command's parser; called once a run, so ``main`` can be called again.
    body : callable
        ``body(args)`` returns the exit status of a normal end.
    statuses : str
        The command's exit statuses, for the docstring of ``main``.
    keep_argv : bool
        Store the arguments as ``args.argv`` (``None`` for ``sys.argv[1:]``), for commands
        that write their own command line into what they produce.

    Returns
    -------
    Main

    """
    def main(argv: Sequence[str] | None = None) -> int:
        def run(args: argparse.Namespace) -> int:
            if keep_argv:
                args.argv = None if argv is None else list(argv)
            return body(args)
        return run_command(prog, build_parser(), run, argv)
    main.__doc__ = (f'Run ``{prog}`` on ``argv`` (default ``sys.argv[1:]``); exit status: '
                    f'{statuses}.')
    main.__module__ = getattr(body, '__module__', __name__)
    return main


def choices(cls: type[Params], name: str) -> tuple[str, ...]:
    """
    Return the allowed strings of parameter ``name`` of group ``cls``, as declared.

    Parameters
    ----------
    cls : type
        A :class:`~piezo_stage_ros.core.contracts.params.Params` group.
    name : str
        Dotted name inside the group, e.g. ``'model'`` or ``'notch.mode'``.

    Returns
    -------
    tuple of str

    Raises
    ------
    ValueError
        If the parameter does not exist or has no choices (a programming error).

    """
    spec: ParamSpec | None = next((s for s in cls.specs() if s.name == name), None)
    if spec is None or spec.choices is None:
        raise ValueError(f'{cls.__name__}.{name} is not a parameter with choices')
    return spec.choices


def add_config_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--config FILE`` (repeatable) and ``--param NODE:NAME=VALUE`` (repeatable)."""
    parser.add_argument('--config', action='append', default=[], metavar='FILE',
                        help='ROS 2 parameter file applied on top of config/default.yaml '
                        '(repeatable; later files win).')
    parser.add_argument('--param', action='append', default=[], metavar='NODE:NAME=VALUE',
                        help='Set one parameter, e.g. controller_node:rac.epsilon_v=0.05 '
                        '(VALUE is YAML; repeatable).')


def add_feedforward_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--feedforward MODE`` (controller_node ``feedforward.mode``)."""
    from piezo_stage_ros.core.control.controllers import ControllerParams
    modes = choices(ControllerParams, 'feedforward.mode')
    parser.add_argument('--feedforward', choices=modes, metavar='MODE',
                        help='Feed-forward mode (controller_node feedforward.mode): '
                        + ', '.join(modes) + '.')


def add_line_options(parser: argparse.ArgumentParser, what: str) -> None:
    """
    Add ``--line-middle F`` and ``--pixels N``: the line figures (core/loop/metrics.py).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The command's parser.
    what : str
        What the command does with them, in the case of the command's other help texts: a
        capital starts a sentence (``'Measure'``), a small letter a phrase (``'measure and
        plot'``).

    """
    def fraction(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = -1.0
        if not 0.0 < value <= 1.0:
            raise argparse.ArgumentTypeError(f'{text!r} is out of range; allowed: (0, 1]')
        return value

    def pixels(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = 0
        if not 1 <= value <= 1_000_000:
            raise argparse.ArgumentTypeError(f'{text!r} is out of range; allowed: a whole '
                                             'number in [1, 1000000]')
        return value
    also = 'Also' if what[:1].isupper() else 'also'
    parser.add_argument('--line-middle', type=fraction, metavar='F', dest='line_middle',
                        help=f'{what} the middle F (0 < F <= 1) of the linear part of each '
                        'line, trace and retrace apart (a scan line: without asking, F = 1; '
                        'a triangle: only when asked).')
    parser.add_argument('--pixels', type=pixels, metavar='N',
                        help=f'{also} {what.lower()} the error at N pixels a line over that '
                        'part.')


def parse_param(text: str) -> tuple[str, str, Any]:
    """
    Split ``NODE:NAME=VALUE``, VALUE read as ROS 2 reads YAML.

    Parameters
    ----------
    text : str
        E.g. ``'controller_node:rac.epsilon_v=0.05'``.

    Returns
    -------
    node, name : str
    value : Any

    Raises
    ------
    ConfigError
        If ``text`` is not of that shape.

    """
    if ':' not in text or '=' not in text:
        raise ConfigError(f'--param {text!r}: expected NODE:NAME=VALUE, e.g. '
                          'controller_node:rac.epsilon_v=0.05')
    node, rest = text.split(':', 1)
    name, raw = rest.split('=', 1)
    if not node or not name:
        raise ConfigError(f'--param {text!r}: expected NODE:NAME=VALUE')
    text = raw.strip()
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        value = text
    # read as ROS 2 (YAML 1.2) does: 'off'/'yes' stay strings, '1e-6' is a float
    if isinstance(value, bool) and text.lower() not in ('true', 'false'):
        value = text
    elif isinstance(value, str):
        try:
            value = float(text)
        except ValueError:
            pass
    return node.strip(), name.strip(), value


def read_config(files: Sequence[str], params: Sequence[str] = ()) -> Config:
    """
    Read ``config/default.yaml``, then ``files``, then the ``--param`` settings.

    Parameters
    ----------
    files : sequence of str
        ``--config`` files, in order: paths, or names of files in the package's ``config/``
        (:func:`~piezo_stage_ros.core.config.loader.find_config`).
    params : sequence of str
        ``--param`` texts, in order.

    Returns
    -------
    Config

    """
    paths = [find_config('default.yaml')]
    # a bare name may be one of the package's files; a path is read as given
    paths += [Path(name) if Path(name).is_file() or os.sep in name else find_config(name)
              for name in files]
    config = load_config(paths)
    for text in params:
        node, name, value = parse_param(text)
        config = config.with_overrides(node, {name: value})
    return config


def loop_overrides(config: Config, *, plant: str | None = None, hysteresis: str | None = None,
                   controller: str | None = None, trajectory: str | None = None,
                   frequencies: Sequence[float] | None = None, amplitude: float | None = None,
                   offset: float | None = None, csv: str | None = None, seed: int | None = None,
                   noise: float | None = None, feedforward: str | None = None) -> Config:
    """
    Apply the short flags of the commands on top of the configuration.

    Parameters
    ----------
    config : Config
        Files and ``--param`` settings.
    plant, hysteresis, controller, trajectory : str, optional
        ``plant.model``, ``hysteresis.model`` (plant_node), ``type`` (controller_node),
        ``kind`` (trajectory_node).
    frequencies : sequence of float, optional
        Frequency of a sine, triangle or scan line (one value) or the multisine components
        [Hz].
    amplitude, offset : float, optional
        Amplitude and offset of the trajectory kind [m] (each kind's own names, e.g. square:
        peak to peak and low level).
    csv : str, optional
        ``csv.path``.
    seed : int, optional
        Sensor-noise seed.
    noise : float, optional
        Sensor noise standard deviation [m].
    feedforward : str, optional
        ``feedforward.mode`` (controller_node).

    Returns
    -------
    Config

    Raises
    ------
    ParameterError
        For a flag that does not apply to the trajectory kind.

    """
    stage: dict[str, Any] = {}
    for name, value in (('plant.model', plant), ('hysteresis.model', hysteresis),
                        ('seed', seed), ('chain.sensor_noise_std_m', noise)):
        if value is not None:
            stage[name] = value
    if stage:
        config = config.with_overrides('plant_node', stage)
    ctrl = {name: value for name, value in (('type', controller),
                                            ('feedforward.mode', feedforward))
            if value is not None}
    if ctrl:
        config = config.with_overrides('controller_node', ctrl)
    traj: dict[str, Any] = {}
    if trajectory is not None:
        traj['kind'] = trajectory
    kind = traj.get('kind', config.node('trajectory_node').get('kind', 'sine'))
    freqs = list(frequencies) if frequencies else []
    if kind in ('sine', 'triangle', 'scan_line'):
        if freqs:
            if len(freqs) > 1:
                raise ParameterError('--frequency', freqs, f'one value for {kind}',
                                     'is repeated; only multisine takes several')
            traj[f'{kind}.frequency_hz'] = freqs[0]
        if amplitude is not None:
            traj[f'{kind}.amplitude_m'] = amplitude
        if offset is not None:
            traj[f'{kind}.offset_m'] = offset
    elif kind == 'multisine':
        current = config.node('trajectory_node')
        n = len(freqs) if freqs else len(current.get('multisine.frequencies_hz', [10.0, 100.0]))
        if freqs:
            traj['multisine.frequencies_hz'] = freqs
        if amplitude is not None:
            traj['multisine.amplitudes_m'] = [amplitude] * n
        elif freqs:
            amps = list(current.get('multisine.amplitudes_m', [1.9e-6, 1.9e-6]))
            if len(amps) != n:
                # keep the total excursion of the configured multisine, shared equally
                traj['multisine.amplitudes_m'] = [sum(amps) / n] * n
        if offset is not None:
            traj['multisine.offset_m'] = offset
    else:
        if freqs:
            raise ParameterError('--frequency', freqs[0], 'sine, triangle, scan_line or '
                                 'multisine',
                                 f'does not apply to trajectory {kind!r}')
        names = {'square': ('square.peak_to_peak_m', 'square.low_m'),
                 'staircase': ('staircase.step_m', 'staircase.start_m'),
                 'step': ('step.final_m', 'step.initial_m'),
                 'noise': ('noise.amplitude_m', 'noise.offset_m'),
                 'chirp': ('chirp.amplitude_m', 'chirp.offset_m')}.get(kind, (None, None))
        for flag, target in ((amplitude, names[0]), (offset, names[1])):
            if flag is not None:
                if target is None:
                    raise ParameterError('--amplitude/--offset', flag,
                                         'not with trajectory ' + repr(kind),
                                         f'does not apply to trajectory {kind!r}')
                traj[target] = flag
    if csv is not None:
        traj['csv.path'] = csv
    if traj:
        config = config.with_overrides('trajectory_node', traj)
    return config


def offline_loop(prog: str, config: Config) -> LoopConfig:
    """
    Build the loop configuration for an offline command and print its notes once.

    Parameters
    ----------
    prog : str
        Program name, for the notes.
    config : Config
        Files, ``--param`` and flags.

    Returns
    -------
    LoopConfig

    """
    loop = LoopConfig.from_config(config)
    for text in loop.offline_notes():
        note(prog, text)
    return loop


class Progress:
    """
    The progress display of a command, on stderr.

    Parameters
    ----------
    prog : str
        Program name (prefix of the percentage line).
    stream : TextIO, optional
        Where to write; default ``sys.stderr``.
    enabled : bool
        Write nothing when false.

    """

    def __init__(self, prog: str, stream: TextIO | None = None, *, enabled: bool = True
                 ) -> None:
        self.prog = prog
        self.stream = sys.stderr if stream is None else stream
        self.enabled = enabled
        self.start = time.perf_counter()
        self._open = False

    def elapsed(self) -> float:
        """Return the seconds since the display was made [s]."""
        return time.perf_counter() - self.start

    def line(self, text: str) -> None:
        """Write ``[  12.3 s] text`` (seconds since the start) on a line of its own."""
        if self.enabled:
            self.end()
            print(f'[{self.elapsed():6.1f} s] {text}', file=self.stream, flush=True)

    def fraction(self, label: str, done: int, total: int, unit: str = 'messages') -> None:
        """Rewrite ``PROG: label  42.0% (done/total unit)`` in place."""
        if self.enabled:
            percent = 100.0 * done / total if total else 100.0
            self.stream.write(f'\r{self.prog}: {label} {percent:5.1f}% ({done}/{total} {unit})')
            self.stream.flush()
            self._open = True

    def end(self) -> None:
        """Clear a percentage line, if one is shown."""
        if self._open:
            self.stream.write('\r\033[K')
            self.stream.flush()
            self._open = False
