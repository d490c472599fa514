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
What the nodes report on ``/diagnostics`` and what their lifecycle allows (no rclpy).

Each function turns a node's counters into one :class:`Status`: its level (OK, WARN, ERROR as
``diagnostic_msgs/DiagnosticStatus`` numbers them), its name ``'<node>: <part>'`` (the prefix
diagnostic_aggregator's analyzers group by), a message and the values as strings with their
units in the keys. :mod:`piezo_stage_ros.nodes.diagnostics` only publishes them.
:class:`StageLifecycle` is what the managed plant node's transitions decide; :class:`GoalGate`
what they mean for goals.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Callable, Mapping, Sequence

from piezo_stage_ros.core.loop.follow import GoalsStatus

__all__ = ['ERROR', 'GoalGate', 'OK', 'STALE', 'StageLifecycle', 'Status', 'WARN',
           'controller_statuses', 'estimates_status', 'goals_of', 'hardware_id',
           'learning_status', 'loop_status', 'stability_status', 'watchdog_status']

#: Levels of ``diagnostic_msgs/DiagnosticStatus``.
OK, WARN, ERROR, STALE = 0, 1, 2, 3

#: Counters of the loop any of which, grown since the last report, make it a warning.
DEGRADED = ('late', 'late_half_period', 'skipped', 'queue_overruns', 'ring_missed',
            'live_dropped')


@dataclass(frozen=True)
class Status:
    """
    One ``DiagnosticStatus`` without rclpy.

    Attributes
    ----------
    level : int
        :data:`OK`, :data:`WARN`, :data:`ERROR` or :data:`STALE`.
    name : str
        ``'<node>: <part>'``.
    message : str
        One line for a reader.
    hardware_id : str
        The hardware the status is about (the backend).
    values : tuple of (str, str)
        Key, value.

    """

    level: int
    name: str
    message: str
    hardware_id: str = ''
    values: tuple[tuple[str, str], ...] = ()


#: A source of statuses for the publisher: called once a report.
StatusSource = Callable[[], Sequence[Status]]


def hardware_id(namespace: str) -> str:
    """
    Return the hardware id every status of one stage carries: ``piezo_stage`` and namespace.

    The nodes of one stage share their namespace (several stages side by side differ in it),
    so that a monitor groups a stage's statuses from every node under one device.
    """
    ns = namespace.strip('/')
    return f'piezo_stage/{ns}' if ns else 'piezo_stage'


def _values(items: Mapping[str, Any]) -> tuple[tuple[str, str], ...]:
    return tuple((str(k), str(v)) for k, v in items.items())


def loop_status(node: str, hardware_id: str, stats: Mapping[str, Any],
                before: Mapping[str, Any] | None, state: str) -> Status:
    """
    Return the loop's status from the plant's counters.

    Parameters
    ----------
    node : str
        The node's name.
    hardware_id : str
        The backend.
    stats : mapping
        The plant node's counters now (``PlantNode.stats``).
    before : mapping or None
        The counters at the last report (None: the first report).
    state : str
        The lifecycle state (``'active'`` ...).

    Returns
    -------
    Status
        ERROR after a fault (``error`` among the counters); WARN when a counter of
        :data:`DEGRADED` grew since the last report; OK otherwise (a stage that is not active
        is OK: it holds the safe voltage).

    """
    grown = [k for k in DEGRADED
             if float(stats.get(k, 0) or 0) > float((before or {}).get(k, 0) or 0)]
    samples = int(stats.get('index', -1)) + 1
    if stats.get('error'):
        level, message = ERROR, f'fault: {stats["error"]}'
    elif grown:
        level, message = WARN, 'degraded: ' + ', '.join(
            f'{k} +{float(stats.get(k, 0) or 0) - float((before or {}).get(k, 0) or 0):g}'
            for k in grown)
    else:
        level, message = OK, f'{state}: {samples} samples'
    keys = ('index', 'samples', 'paced_samples', 'commands', 'late', 'late_half_period',
            'skipped', 'lateness_p99_us', 'lateness_max_us', 'queue_overruns', 'resends',
            'samples_per_s', 'real_time_factor')
    values = {'state': state, **{k: stats[k] for k in keys if k in stats}}
    return Status(level, f'{node}: loop', message, hardware_id, _values(values))


def watchdog_status(node: str, hardware_id: str, stats: Mapping[str, Any],
                    before: Mapping[str, Any] | None, applied_v: float,
                    phase: str) -> Status:
    """
    Return the watchdog's status.

    ERROR while the guard ramps to or holds the safe voltage in a run (``phase`` ``'ramp'``
    or ``'safe'``); WARN when it tripped since the last report and has recovered; OK
    otherwise. ``applied_v``: the voltage applied last [V]; ``phase``:
    ``GuardedPlant.phase``.
    """
    trips = int(stats.get('watchdog_trips', 0) or 0)
    new = trips - int((before or {}).get('watchdog_trips', 0) or 0)
    if phase in ('ramp', 'safe'):
        level, message = ERROR, f'tripped: {phase} (commands stopped)'
    elif new > 0:
        level, message = WARN, f'{new} trip(s) since the last report, recovered'
    else:
        level, message = OK, 'fed'
    values = {'trips': trips, 'phase': phase, 'applied_v': f'{applied_v:.6g}',
              'ramp_samples': stats.get('ramp_samples', 0),
              'max_step_v': stats.get('watchdog_max_step_v', 0.0)}
    return Status(level, f'{node}: watchdog', message, hardware_id, _values(values))


def estimates_status(node: str, hardware_id: str, names: Sequence[str],
                     values: Sequence[float],
                     bounds: Mapping[str, tuple[float, float]]) -> Status | None:
    """
    Return the adaptive estimates' status, or None for a controller without estimates.

    ``names``, ``values``: the controller's diagnostics; ``bounds``: ``{'theta_hat': (low,
    high), ...}``, the projection's box. WARN when an estimate sits on a bound (the
    projection holds it: the true value may lie outside the box), ERROR when one is not
    finite, OK otherwise.
    """
    found = {n: float(v) for n, v in zip(names, values) if n in bounds}
    if not found:
        return None
    at_bound = []
    bad = []
    for name, value in found.items():
        low, high = bounds[name]
        if not math.isfinite(value):
            bad.append(name)
        elif value <= low or value >= high:
            at_bound.append(f'{name} at {"lower" if value <= low else "upper"} bound')
    if bad:
        level, message = ERROR, 'not finite: ' + ', '.join(bad)
    elif at_bound:
        level, message = WARN, '; '.join(at_bound)
    else:
        level, message = OK, 'inside the projection box'
    out: dict[str, Any] = {}
    for name, value in found.items():
        out[name] = f'{value:.9g}'
        out[f'{name}_bounds'] = f'[{bounds[name][0]:g}, {bounds[name][1]:g}]'
    return Status(level, f'{node}: estimates', message, hardware_id, _values(out))


def learning_status(node: str, hardware_id: str, names: Sequence[str],
                    values: Sequence[float], before_rms_m: float | None,
                    growth: float = 1.5) -> Status | None:
    """
    Return the feed-forward learning's status, or None without a learning feed-forward.

    WARN when the last learned period's rms error grew by more than ``growth`` times since
    the last report (the learning does not converge), or when the trajectory does not match
    the learned one (``ff_active`` 0 after periods were learned); OK otherwise.
    """
    got = dict(zip(names, values))
    if 'ff_periods_learned' not in got:
        return None
    periods = int(got['ff_periods_learned'])
    rms = float(got.get('ff_period_rms_m', math.nan))
    active = bool(got.get('ff_active', 0.0))
    if before_rms_m is not None and math.isfinite(rms) and math.isfinite(before_rms_m) \
            and before_rms_m > 0.0 and rms > growth * before_rms_m:
        level, message = WARN, (f'not converging: period rms {rms:.3g} m, '
                                f'was {before_rms_m:.3g} m')
    elif periods > 0 and not active:
        level, message = WARN, 'learned table does not match the trajectory: not applied'
    else:
        level, message = OK, f'{periods} periods learned'
    out = {'periods_learned': periods, 'period_rms_m': f'{rms:.6g}',
           'active': int(active), 'mismatches': int(got.get('ff_mismatches', 0))}
    return Status(level, f'{node}: learning', message, hardware_id, _values(out))


def stability_status(node: str, hardware_id: str, verdict: str, stable: bool,
                     caution: bool) -> Status:
    """
    Return the stability check's verdict as a status.

    ERROR when the loop was found unstable (the node runs it because ``stability.action``
    says warn), WARN for a stable loop with a caution (adaptation rates that can limit-cycle),
    OK otherwise; the verdict's text is the message.
    """
    level = ERROR if not stable else (WARN if caution else OK)
    return Status(level, f'{node}: stability', verdict.splitlines()[0] if verdict else '',
                  hardware_id, (('verdict', verdict),))


def controller_statuses(node: str, hw_id: str, diagnostics: tuple[Sequence[str],
                                                                  Sequence[float]] | None,
                        bounds: Mapping[str, tuple[float, float]], verdict: str, stable: bool,
                        caution: bool, before_rms_m: float | None) -> list[Status]:
    """
    Return the controller node's statuses: stability, and estimates and learning if any.

    ``diagnostics``: the controller's last ``(names, values)`` (None before the first);
    ``bounds``: the projection box of the estimates (:func:`estimates_status`);
    ``before_rms_m``: the learned period's rms error at the last report (
    :func:`learning_status`).
    """
    out = [stability_status(node, hw_id, verdict, stable, caution)]
    if diagnostics is not None:
        names, values = diagnostics
        for status in (estimates_status(node, hw_id, names, values, bounds),
                       learning_status(node, hw_id, names, values, before_rms_m)):
            if status is not None:
                out.append(status)
    return out


def goals_of(node: str, hardware_id: str, goals: GoalsStatus) -> Status:
    """
    Return the goals' status as ``'<node>: goals'``.

    OK, or WARN for a while after a goal violated a tolerance
    (:func:`~piezo_stage_ros.core.loop.follow.goals_status`).
    """
    return Status(goals.level, f'{node}: goals', goals.message, hardware_id, goals.values)


class StageLifecycle:
    """
    What the managed plant node's transitions allow, apart from rclpy's state machine.

    rclpy's machine decides which transition is possible from which state; this adds the
    stage's own rule: a run activated once and deactivated (or complete) is not resumed, as
    its samples, time base and controller state ended with it. A new run is another process
    (or, for the plant alone, a cleanup and a configure).

    Attributes
    ----------
    configured : bool
        Between a successful configure and a cleanup.
    ran : bool
        A run was activated since the last configure.
    active : bool
        Between a successful activate and a deactivate.

    """

    def __init__(self) -> None:
        self.configured = False
        self.ran = False
        self.active = False

    def configure(self) -> str | None:
        """Return None when configure may proceed, else why not."""
        if self.configured:
            return 'already configured'
        return None

    def configured_ok(self) -> None:
        """Record a successful configure."""
        self.configured, self.ran, self.active = True, False, False

    def activate(self) -> str | None:
        """Return None when activate may proceed, else why not."""
        if not self.configured:
            return 'not configured'
        if self.ran:
            return ('this run was activated once and ended; a stopped run is not resumed: '
                    'cleanup and configure for a new one')
        return None

    def activated(self) -> None:
        """Record a successful activate."""
        self.ran = self.active = True

    def deactivated(self) -> None:
        """Record a deactivate (the stage ramped to the safe voltage)."""
        self.active = False

    def cleaned_up(self) -> None:
        """Record a cleanup (the backend released)."""
        self.configured = self.ran = self.active = False


class GoalGate:
    """
    Whether goals may run, from the plant node's lifecycle state as last heard.

    A goal moves the stage only while the plant node is active (its loop runs); as
    joint_trajectory_controller takes goals only while it is active and ends its goal when
    deactivated. Until a state is heard (no managed plant node, or none found yet) goals are
    taken, as a node without a lifecycle would take them.

    Attributes
    ----------
    state : str or None
        The plant's state label (``'active'``, ``'deactivating'``, ``'inactive'`` ...; a
        label of rclpy's lifecycle or ``'faulted'``), None before any was heard.

    """

    def __init__(self) -> None:
        self.state: str | None = None

    def refusal(self) -> str | None:
        """Return why a goal arriving now is refused, or None when it may run."""
        if self.state is None or self.state == 'active':
            return None
        return (f'the plant node is {self.state}: goals are taken only while it is active '
                '(ros2 lifecycle set <namespace>/plant_node activate)')

    def update(self, state: str) -> str | None:
        """
        Take the plant's new state; return why the running goals end now, or None.

        They end when the plant leaves the active state (a deactivate, a cleanup or a
        shutdown from active, an error, a fault): its loop no longer follows them and the
        stage ramps to the safe voltage at the watchdog's slew.
        """
        was, self.state = self.state, state
        if state == 'active' or was not in (None, 'active'):
            return None
        return (f'the plant node left the active state ({state}): the goal ended; the stage '
                'ramps to the safe voltage at watchdog.slew_v_per_s and holds there')
