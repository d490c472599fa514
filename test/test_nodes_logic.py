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

"""The nodes' behaviour without rclpy: tables, sequencing, real-time sampling, watchdogs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from piezo_stage_ros.core.config.axes import has_axes
from piezo_stage_ros.core.config.loader import load_config
from piezo_stage_ros.core.contracts.errors import ParameterError, PiezoStageError
from piezo_stage_ros.core.contracts.params import param, Params
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.stage import StageParams
from piezo_stage_ros.hardware.bridge import ModelBridge
from piezo_stage_ros.hardware.safety import GuardedPlant
from piezo_stage_ros.nodes.logic import (
    ControllerLogic,
    PlantLogic,
    rebuild_or_learn_afresh,
    sample_count,
    TrajectoryLogic,
)
from piezo_stage_ros.nodes.tables import (
    controller_table,
    feedforward_context,
    Group,
    NodeTable,
    plant_table,
    PlantNodeParams,
    trajectory_table,
)
import pytest

CONFIG = Path(__file__).resolve().parents[1] / 'config'
TABLES = {'plant_node': plant_table, 'controller_node': controller_table,
          'trajectory_node': trajectory_table}
RATE = 10000.0


# --- topics and tables --------------------------------------------------------------------

@pytest.mark.parametrize('node', sorted(TABLES))
def test_every_row_has_unit_description_and_a_valid_default(node):
    table = TABLES[node]()
    rows = table.specs()
    assert len({r.name for r in rows}) == len(rows)
    for row in rows:
        assert row.unit and row.description.endswith('.'), row.name
        assert row.validate(row.default) is not None or row.type_name == 'string'
    table.build({})
    for decl in table.declarations():
        spec = next(r for r in rows if r.name == decl.name)
        if spec.unit != '-':
            assert decl.description.endswith(f'[{spec.unit}]')
        assert decl.additional_constraints == spec.allowed()
        both = spec.low is not None and spec.high is not None
        assert (decl.float_range is not None) == (both and spec.type_name == 'double')
        assert (decl.int_range is not None) == (both and spec.type_name == 'integer')


# a multi-axis file (plant_node axes.names) is not a one-axis node file: test_axes_config.py
SCENARIOS = sorted(p.name for p in CONFIG.glob('*.yaml') if p.name not in ('default.yaml',
                                                                           'record_qos.yaml')
                   and not has_axes(load_config([p])))


@pytest.mark.parametrize('scenario', ['default.yaml', *SCENARIOS])
def test_every_shipped_parameter_file_builds_every_node(scenario):
    files = [CONFIG / 'default.yaml'] + ([CONFIG / scenario] if scenario != 'default.yaml'
                                         else [])
    config = load_config(files)
    for node, make in TABLES.items():
        values = {k: v for k, v in config.node(node).items() if k != 'use_sim_time'}
        # strict: a key no node declares would be silently ignored by ROS
        make().build(values)


def test_the_plant_stage_is_start_up_only_and_the_node_group_is_not():
    table = plant_table()
    rows = {r.name: r for r in table.specs()}
    assert rows['plant.third_order.gain'].read_only
    assert rows['chain.safe_voltage_v'].read_only
    assert not rows['command_timeout_s'].read_only and rows['mode'].read_only


def test_run_time_changes_are_validated_naming_parameter_value_and_range():
    table = controller_table()
    current = table.build({})
    new = table.change(current, {'pi.k_p': 2})
    assert new[0].pi.k_p == 2.0 and new[1] is current[1] and new[2] is current[2]
    with pytest.raises(ParameterError, match=r"'type' = 'pi' is read-only"):
        table.change(current, {'type': 'pi'})
    with pytest.raises(ParameterError, match=r"'position_timeout_s' = -1.0 is out of range; "
                                             r'allowed: finite number in \(0, 10\]'):
        table.change(current, {'position_timeout_s': -1.0})
    with pytest.raises(ParameterError, match="'pi.k_p' = 'fast' is not a number"):
        table.change(current, {'pi.k_p': 'fast'})
    with pytest.raises(ParameterError, match="'pi.k_q' = 1 is not a parameter of this node"):
        table.change(current, {'pi.k_q': 1})
    with pytest.raises(ParameterError, match="'stability.slope_max'"):
        table.change(current, {'stability.slope_max': 0.1})
    traj = trajectory_table()
    now = traj.build({})
    with pytest.raises(ParameterError, match='sine'):
        traj.change(now, {'sine.amplitude_m': 1.0})  # leaves the stage travel


def test_duplicate_names_are_refused_and_markdown_lists_every_row():
    @__import__('dataclasses').dataclass(frozen=True)
    class Clash(Params):
        mode: str = param('x', unit='-', description='Clash.')

    with pytest.raises(ValueError, match="'mode' is declared twice"):
        NodeTable('n', [PlantNodeParams, Group(Clash)])
    text = plant_table().markdown()
    for row in plant_table().specs():
        assert f'| `{row.name}` |' in text


# --- plain-value helpers ------------------------------------------------------------------

def test_sample_counts():
    assert sample_count(0.1, RATE) == 1000 and sample_count(0.0, RATE) == 0
    assert sample_count(1e-9, RATE) == 1


# --- plant ----------------------------------------------------------------------------------

def plant(mode: str, duration_s: float = 0.0, **kwargs) -> PlantLogic:
    params = StageParams.from_flat({'plant.model': 'reduced'})
    guard = GuardedPlant(ModelBridge(params), params.chain, command_timeout_s=0.01)
    return PlantLogic(guard, mode=mode, sample_rate_hz=RATE, duration_s=duration_s, **kwargs)


def test_lockstep_plant_waits_resends_and_ignores_unexpected_commands():
    logic = plant('lockstep', duration_s=0.0003, resend_s=0.5)
    assert logic.on_command(1.0, 0.0) is None and logic.unexpected == 1  # before start
    s0 = logic.start(10.0)
    assert (s0.index, s0.stamp_ns) == (0, 0)
    assert logic.resend_due(10.49) is None
    assert logic.resend_due(10.5) == s0 and logic.resend_due(10.6) is None
    s1 = logic.on_command(1.0, 10.7)
    assert (s1.index, s1.stamp_ns) == (1, 100_000)
    assert logic.resend_due(11.1) is None  # the clock restarted with the new sample
    s2 = logic.on_command(1.0, 11.2)
    assert s2.index == 2
    assert logic.on_command(1.0, 11.3) is None and logic.done  # 3 samples: complete
    assert logic.on_command(1.0, 11.4) is None and logic.unexpected == 2
    assert logic.resend_due(99.0) is None
    assert logic.plant.samples == 3 and logic.resends == 1


def test_lockstep_run_of_one_sample_is_done_at_start():
    logic = plant('lockstep', duration_s=1e-6)
    logic.start(0.0)
    assert logic.done and logic.on_command(0.0, 0.0) is None


def test_plant_refuses_an_unknown_mode():
    # real-time sampling is the servo loop's (test/test_servo.py)
    with pytest.raises(ParameterError, match="'mode' = 'fast'"):
        plant('fast')


# --- trajectory -----------------------------------------------------------------------------

def sine() -> object:
    return make_trajectory(TrajectoryParams.from_flat({'kind': 'sine'}))


def test_trajectory_answers_each_stamp_with_the_offline_times():
    traj = sine()
    logic = TrajectoryLogic(traj, sample_rate_hz=RATE, chunk_s=0.01)
    start = 7_000_000_000
    ks = [0, 1, 2, 99, 100, 101, 250, 3]
    got = [logic.on_position(start + k * 100_000) for k in ks]
    ref, vel = traj.evaluate(np.array(ks, dtype=float) * (1.0 / RATE))
    # the same times k / RATE through the same np.sin/np.cos, in a chunk there, eight here: equal
    # on this machine; 1e-18 m (1000 ulp of 7.6e-6 m) and 1e-12 (no zero of the velocity among
    # these k) leave room for a SIMD loop that rounds its tail elements an ulp or two otherwise
    np.testing.assert_allclose([g[0] for g in got], ref, rtol=0, atol=1e-18)
    np.testing.assert_allclose([g[1] for g in got], vel, rtol=1e-12)
    assert logic.on_position(start - 100_000)[0] == got[0][0]  # older than the start


def test_trajectory_start_stop_and_switch_take_effect_at_the_next_sample():
    logic = TrajectoryLogic(sine(), sample_rate_hz=RATE, active=False)
    x0 = sine().evaluate(np.zeros(1))[0][0]
    assert logic.on_position(0) == (x0, 0.0)          # inactive: hold x_d(0)
    logic.start()
    assert logic.on_position(500_000) == (x0, logic.on_position(500_000)[1])
    moving = logic.on_position(600_000)
    assert moving[0] != x0
    logic.stop()
    assert logic.on_position(700_000) == (moving[0], 0.0)  # holds the last reference
    logic.start()
    assert logic.on_position(800_000)[0] == x0         # restarts at t = 0
    square = make_trajectory(TrajectoryParams.from_flat({'kind': 'square'}))
    logic.switch(square)
    assert logic.on_position(900_000)[0] == square.evaluate(np.zeros(1))[0][0]


# --- controller -----------------------------------------------------------------------------

def pi_controller(kp: float = 1.5) -> object:
    return build_controller(ControllerParams.from_flat({'type': 'pi', 'pi.k_p': kp}), 1e-4)


def test_controller_steps_once_per_stamp_whatever_the_order():
    logic = ControllerLogic(pi_controller(), diagnostics_every=2)
    assert logic.on_reference(0, 4e-6, 0.0) is None
    first = logic.on_position(0, 3.8e-6, 0.0)
    assert first is not None and first.stamp_ns == 0 and first.diagnostics is not None
    assert len(first.diagnostics) == len(logic.names) > 0
    assert logic.on_position(0, 3.8e-6, 0.0) is None                 # the same sample again
    assert logic.on_reference(0, 4e-6, 0.0) is None
    assert logic.on_position(100_000, 3.9e-6, 0.0) is None           # waits for its reference
    second = logic.on_reference(100_000, 4e-6, 0.0)
    assert second.stamp_ns == 100_000 and second.diagnostics is None  # every 2nd sample
    logic.on_position(200_000, 3.9e-6, 0.0)
    assert logic.on_reference(100_000, 4e-6, 0.0) is None            # old reference: no pair
    assert logic.on_reference(200_000, 4e-6, 0.0).diagnostics is not None
    assert logic.steps == 3 and logic.duplicates >= 1


def test_controller_matches_a_plain_loop():
    reference = pi_controller()
    logic = ControllerLogic(pi_controller())
    reference.reset(3.8e-6, 4e-6)
    for k in range(50):
        y, xd, vd = 3.8e-6 + 1e-9 * k, 4e-6 + 2e-9 * k, 2e-5
        logic.on_position(k * 100_000, y, 0.0)
        assert logic.on_reference(k * 100_000, xd, vd).voltage_v == reference.step(y, xd, vd)


def test_controller_watchdog_realtime_only_and_reset_after_silence():
    rt = ControllerLogic(pi_controller(), mode='realtime', safe_voltage_v=0.5,
                         position_timeout_s=0.01)
    assert rt.on_check(1.0) is None                   # unarmed before the first position
    rt.on_position(0, 3.8e-6, 1.0)
    rt.on_reference(0, 4e-6, 0.0)
    assert rt.on_check(1.005) is None
    out = rt.on_check(1.02)
    assert out.voltage_v == 0.5 and out.stamp_ns == -1 and rt.watchdog.trips == 1
    rt.on_position(100_000, 3.8e-6, 1.03)
    fresh = pi_controller()
    fresh.reset(3.8e-6, 4e-6)
    assert rt.on_reference(100_000, 4e-6, 0.0).voltage_v == fresh.step(3.8e-6, 4e-6, 0.0)
    ls = ControllerLogic(pi_controller(), mode='lockstep', position_timeout_s=0.01)
    ls.on_position(0, 3.8e-6, 0.0)
    assert ls.on_check(100.0) is None


def test_a_feedforward_keeps_its_reference_index_over_skips_and_resets():
    # real time: the servo skips samples (stamps jump) and a silence resets the controller; the
    # feed-forward must stay on the reference of each stamp (a wrong index is a mismatch)
    from piezo_stage_ros.core.control.feedforward import FeedForwardController
    from piezo_stage_ros.core.model.hysteresis import HysteresisParams, make_hysteresis
    from piezo_stage_ros.core.model.stage import linear_plant
    params = ControllerParams().with_flat({'feedforward.mode': 'inverse'})
    sine = make_trajectory(TrajectoryParams.from_flat({'kind': 'sine'}))
    ctrl = build_controller(params, 1e-4, linear_plant(StageParams().plant),
                            make_hysteresis(HysteresisParams()))
    assert isinstance(ctrl, FeedForwardController)
    ctrl.bind(sine)
    logic = ControllerLogic(ctrl, mode='realtime', position_timeout_s=0.01)
    xd, vd = sine.evaluate(np.arange(400) * 1e-4)

    def sample(k: int, now_s: float) -> None:
        logic.on_position(k * 100_000, 3.8e-6, now_s)
        assert logic.on_reference(k * 100_000, float(xd[k]), float(vd[k])) is not None

    for k in (0, 1, 2, 7, 8, 30):                    # 4 and 21 samples skipped
        sample(k, 1.0)
    assert logic.on_check(1.02) is not None          # silence: the safe command, then a reset
    for k in (250, 251, 399):
        sample(k, 1.03)
    assert ctrl.mismatches == 0 and ctrl.diagnostics()['ff_active'] == 1.0


def test_gain_changes_apply_at_the_next_sample():
    built = []

    def rebuild(params):
        built.append(params)
        return build_controller(params, 1e-4)

    # a gain change is applied in place at the next sample, keeping the integral (no notch
    # here, so the command is the PI law itself)
    plain = {'type': 'pi', 'notch.mode': 'off'}
    logic = ControllerLogic(build_controller(ControllerParams.from_flat(plain), 1e-4),
                            rebuild=rebuild)
    logic.on_position(0, 3.8e-6, 0.0)
    before = logic.on_reference(0, 4e-6, 0.0).voltage_v
    new = ControllerParams.from_flat({**plain, 'pi.k_p': 3.0})
    logic.request_change(new)
    logic.on_position(100_000, 3.8e-6, 0.0)
    after = logic.on_reference(100_000, 4e-6, 0.0).voltage_v
    assert built == [] and logic.changes == 1
    e = (4e-6 - 3.8e-6) * (10 / 38e-6)
    integral = 2 * 1e-4 * e                    # two samples of the same error
    assert after == pytest.approx(3.0 * e + 1500.0 * integral, rel=1e-12)
    assert after != before
    # a structural change (PI -> RAC) builds a new controller, started afresh
    rac = ControllerParams.from_flat({'type': 'rac'})
    logic.request_change(rac)
    logic.on_position(200_000, 3.8e-6, 0.0)
    got = logic.on_reference(200_000, 4e-6, 0.0).voltage_v
    assert built == [rac] and logic.changes == 2
    check = build_controller(rac, 1e-4)
    check.reset(3.8e-6, 4e-6)
    assert got == check.step(3.8e-6, 4e-6, 0.0)

    class Updatable:
        sample_time_s = 1e-4
        gain = 1.0

        def reset(self, position_m, reference_m):
            pass

        def step(self, position_m, reference_m, reference_velocity_mps):
            return self.gain

        def diagnostics(self):
            return {}

        def update_params(self, params):
            self.gain = params
            return True                                # applied in place

    keep = ControllerLogic(Updatable())
    keep.request_change(2.0)
    keep.on_position(0, 0.0, 0.0)
    assert keep.on_reference(0, 0.0, 0.0).voltage_v == 2.0
    stuck = ControllerLogic(pi_controller())
    stuck.request_change(ControllerParams.from_flat({'type': 'rac'}))
    stuck.on_position(0, 0.0, 0.0)
    with pytest.raises(PiezoStageError, match='update_params'):
        stuck.on_reference(0, 0.0, 0.0)


# --- layers ---------------------------------------------------------------------------------

ROS_ROOTS = {'rclpy', 'rcl_interfaces', 'sensor_msgs', 'std_msgs', 'rosgraph_msgs',
             'builtin_interfaces', 'diagnostic_msgs', 'std_srvs', 'launch', 'launch_ros'}
PACKAGE = Path(__file__).resolve().parents[1] / 'piezo_stage_ros'
RCLPY_FREE = sorted([PACKAGE / 'nodes' / f'{m}.py' for m in ('logic', 'tables')]
                    + [PACKAGE / 'core' / 'contracts' / f'{m}.py' for m in ('wire', 'cdr')]
                    + list((PACKAGE / 'hardware').glob('*.py')))


def imported_roots(path: Path) -> set[str]:
    import ast
    roots = set()
    for node in ast.walk(ast.parse(path.read_text(encoding='utf8'))):
        if isinstance(node, ast.Import):
            roots.update(alias.name.split('.')[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            roots.add(node.module.split('.')[0])
    return roots


@pytest.mark.parametrize('path', RCLPY_FREE, ids=lambda p: f'{p.parent.name}/{p.name}')
def test_the_testable_node_modules_never_import_ros(path):
    assert not imported_roots(path) & ROS_ROOTS


def test_the_testable_node_modules_import_with_ros_blocked():
    import subprocess
    import sys
    code = (
        'import sys\n'
        'class Block:\n'
        '    def find_spec(self, name, path=None, target=None):\n'
        f'        if name.split(".")[0] in {sorted(ROS_ROOTS)!r}:\n'
        '            raise ImportError("blocked: " + name)\n'
        'sys.meta_path.insert(0, Block())\n'
        'import piezo_stage_ros.nodes.logic, piezo_stage_ros.nodes.tables\n'
        'import piezo_stage_ros.core.contracts.wire, piezo_stage_ros.core.contracts.cdr\n'
        'import piezo_stage_ros.hardware.emulator, piezo_stage_ros.hardware.udp\n'
        'import piezo_stage_ros.bench.ros\n'
        'print("ok")\n')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         cwd=PACKAGE.parent, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == 'ok'


def test_gate_looks_every_n_calls():
    from piezo_stage_ros.nodes.logic import Gate
    counts = iter([0, 2, 0])
    looked = []

    def count():
        looked.append(True)
        return next(counts)

    gate = Gate(count, every=3)
    assert [gate() for _ in range(9)] == [False] * 3 + [True] * 3 + [False] * 3
    assert len(looked) == 3


# --- what the plant node says to the user (it only logs at the severity returned) ------------

def test_real_time_by_messages_warns_at_once_and_names_the_direct_composition():
    from piezo_stage_ros.nodes.logic import realtime_warning
    assert realtime_warning('lockstep', False, 1e4) is None
    assert realtime_warning('realtime', True, 1e4) is None
    text = realtime_warning('realtime', False, 1e4)
    assert text is not None and 'direct:=true' in text and 'stage_servo --direct' in text
    assert '10000 Hz' in text


def test_the_end_of_run_line_is_a_warning_past_the_thresholds():
    from piezo_stage_ros.nodes.logic import LATE_HALF_LIMIT, run_verdict
    clean = {'paced_samples': 600_000, 'samples': 599_999, 'late': 0, 'late_half_period': 600,
             'skipped': 0, 'ring_missed': 0, 'queue_overruns': 0, 'watchdog_trips': 0}
    assert 600 <= LATE_HALF_LIMIT * 600_000 and run_verdict(clean) == ('info', [])
    assert run_verdict({'samples': 5000, 'index': 4999, 'watchdog_trips': 0}) == ('info', [])
    level, why = run_verdict(dict(clean, late_half_period=601))
    assert level == 'warn' and why == ['601 samples (0.1 %) late by more than T/2 (threshold '
                                       '0.1 %)']
    level, why = run_verdict(dict(clean, late=522_000, skipped=3, ring_missed=1,
                                  watchdog_trips=773))
    assert level == 'warn' and len(why) == 4
    assert why[0].startswith('522000 samples (87 %) served with the previous command')
    assert why[1:] == ['3 skipped', '1 lost between the servo process and the node '
                       '(ring_missed)', '773 watchdog trips']
    assert run_verdict(dict(clean, bridge_lost=2))[0] == 'warn'


def test_each_trip_is_logged_with_its_length_and_largest_step_at_most_once_a_second():
    from piezo_stage_ros.hardware.safety import Trip
    from piezo_stage_ros.nodes.logic import TripLog

    def trip(n, step=0.01):
        return Trip(start_s=0.0, silence_s=0.0123, start_sample=0, from_v=4.0, samples=n,
                    ramp_samples=n - 1, safe_samples=0, recovery_samples=1, max_step_v=step,
                    duration_s=n * 1e-4, ended='commands')

    log = TripLog(0.0)
    kw = {'slew_v_per_s': 100.0, 'period_s': 1e-4}
    (line,) = log.lines([trip(41)], 10.0, **kw)
    assert line == ('watchdog trip: no command for 12.3 ms; 41 samples over 4.1 ms: 40 ramping '
                    'from 4 V toward the safe 0 V, 0 at it, 1 following the commands back; '
                    'largest step 0.01 V (watchdog.slew_v_per_s 100 allows 0.01 V a sample); '
                    'ended: the commands reached again')
    # within the second: counted, said with the next line
    assert log.lines([trip(5), trip(7, 0.002)], 10.5, **kw) == []
    assert log.lines([], 10.9, **kw) == []
    (line,) = log.lines([trip(3)], 11.2, **kw)
    assert line.endswith('(and 2 more trips since the last line: 12 samples, largest step '
                         '0.01 V)')
    assert log.lines([trip(2)], 11.3, **kw) == []
    assert log.lines([], 12.4, **kw) == ['watchdog: 1 more trips since the last line: 2 '
                                         'samples, largest step 0.01 V']
    assert log.lines([trip(2)], 12.5, **kw) == []
    assert len(log.lines([], 12.6, final=True, **kw)) == 1


def test_a_rebuild_learns_afresh_when_the_table_no_longer_fits():
    # a change the table was not learned with: the new controller starts from zero, warned;
    # a refusal for another reason stays a refusal
    ff = ControllerParams().feedforward.replace(mode='learning', table_file='old.npz')
    params = ControllerParams().replace(feedforward=ff)
    built, told = [], []

    def build(p: ControllerParams) -> object:
        if p.feedforward.table_file:
            raise ParameterError('feedforward.table_file', p.feedforward.table_file, 'a match')
        built.append(p)
        return object()

    rebuild_or_learn_afresh(build, params, told.append)  # type: ignore[arg-type]
    assert built[0].feedforward.table_file == '' and built[0].feedforward.mode == 'learning'
    assert len(told) == 1 and 'old.npz' in told[0]

    def refuse(p: ControllerParams) -> object:
        raise ParameterError('rac.k_d', -1.0, '> 0')

    with pytest.raises(ParameterError, match='rac.k_d'):
        rebuild_or_learn_afresh(refuse, params.replace(feedforward=ff.replace(table_file='')),
                                told.append)  # type: ignore[arg-type]
    assert len(told) == 1


def test_a_feed_forward_check_is_told_the_period_and_the_stage():
    # no files: the defaults the other two nodes start from (a 100 Hz sine, the paper's stage)
    (hysteresis, reference), check = feedforward_context([])
    assert reference.period_s == pytest.approx(0.01) and check['period_s'] == reference.period_s
    assert check['stage'] == StageParams() and hysteresis is not None


@pytest.mark.parametrize('verdict', ['info', 'warn'])
def test_the_ros_benchmark_reads_the_end_of_run_line_at_either_severity(verdict):
    # the line the plant node logs (run_verdict decides its severity); the benchmark parses the
    # launch's output without rclpy
    from piezo_stage_ros.bench.ros import end_of_run_figures
    stats = {'samples': 599746, 'late_half_period': 1221, 'skipped': 253, 'wall_s': 60.9,
             'servo_nice': 'applied: -20'}
    if verdict == 'warn':
        head = 'run complete, degraded (1221 samples (0.2 %) late by more than T/2; 253 skipped)'
    else:
        head = 'run complete'
    figures = ', '.join(f'{k}={v}' for k, v in stats.items())
    log = f'[stage_servo-1] [INFO] [1.5] [plant_node]: {head}: {figures}\n[INFO] done\n'
    assert end_of_run_figures(log) == stats
    with pytest.raises(RuntimeError, match='no end-of-run line'):
        end_of_run_figures('[INFO] nothing here')


def test_references_ahead_go_on_after_a_switch_and_the_switch_says_where_it_started():
    # lockstep_ahead: after a new trajectory the references ahead must go on from where they
    # were (a stall would leave the controller without a reference until each resend)
    first = make_trajectory(TrajectoryParams.from_flat({'kind': 'sine'}))
    second = make_trajectory(TrajectoryParams.from_flat({'kind': 'sine',
                                                         'sine.frequency_hz': 137.0}))
    logic = TrajectoryLogic(first, sample_rate_hz=1e4)
    period_ns = 100_000
    sent = []
    for k in range(60):
        if k == 30:
            logic.switch(second)
        out = logic.ahead(k * period_ns, 4)
        sent += [stamp // period_ns for stamp, _, _ in out]
        if k == 30:
            # the switch falls on the first sample not yet sent: 30 + 4
            assert logic.take_switch() == 34 * period_ns
        else:
            assert logic.take_switch() is None
    assert sent == list(range(64))
    # the second trajectory from its t = 0 at sample 34, on the same stamps
    again = TrajectoryLogic(second, sample_rate_hz=1e4)
    again.on_position(34 * period_ns)
    assert logic.on_position(50 * period_ns) == again.on_position(50 * period_ns)


def test_references_ahead_while_inactive_hold_and_a_start_sends_them_again():
    sine = make_trajectory(TrajectoryParams.from_flat({'kind': 'sine'}))
    logic = TrajectoryLogic(sine, sample_rate_hz=1e4, active=False)
    first = [s for s, _, _ in logic.ahead(0, 3)] + [s for s, _, _ in logic.ahead(100_000, 3)]
    assert first == [0, 100_000, 200_000, 300_000, 400_000]
    logic.start()
    again = logic.ahead(200_000, 3)
    # t = 0 at the start's sample, and the samples after it again with the started reference
    assert [s for s, _, _ in again] == [200_000, 300_000, 400_000, 500_000]
    assert [x for _, x, _ in again] == sine.evaluate(np.arange(4) * 1e-4)[0].tolist()


@pytest.mark.parametrize('late', [-3, 0, 2])
def test_an_announced_trajectory_is_bound_at_the_stamp_of_its_t0(late):
    # a controller in another node: the announcement of the new trajectory comes before its
    # t = 0 (late < 0), at it, or after (late > 0 samples already stepped); the feed-forward
    # must predict from the reference that plays at every stamp (a wrong one is a mismatch)
    from piezo_stage_ros.core.control.feedforward import FeedForwardController
    from piezo_stage_ros.core.model.hysteresis import HysteresisParams, make_hysteresis
    from piezo_stage_ros.core.model.stage import linear_plant
    from piezo_stage_ros.nodes.logic import announce_trajectory, parse_trajectory
    params = ControllerParams().with_flat({'feedforward.mode': 'inverse_learning'})
    first_p = TrajectoryParams.from_flat({'kind': 'sine'})
    second_p = TrajectoryParams.from_flat({'kind': 'sine', 'sine.frequency_hz': 137.0})
    first = make_trajectory(first_p)
    ctrl = build_controller(params, 1e-4, linear_plant(StageParams().plant),
                            make_hysteresis(HysteresisParams()))
    assert isinstance(ctrl, FeedForwardController)
    ctrl.bind(first)
    logic = ControllerLogic(ctrl)
    refs = TrajectoryLogic(first, sample_rate_hz=1e4)
    # the text a trajectory node sends once t = 0 of the new one has its stamp (ahead of the
    # controller's sample with lockstep_ahead: late < 0)
    text = announce_trajectory(250 * 100_000, second_p)
    switch_k = None
    for k in range(700):
        stamp = k * 100_000
        if k == 250:
            refs.switch(make_trajectory(second_p))
        x, v = refs.on_position(stamp)
        at = refs.take_switch()
        if at is not None:
            switch_k = k
            assert at == stamp
        if k == 250 + late:
            at_ns, got = parse_trajectory(text)
            assert got == second_p and at_ns == 250 * 100_000
            logic.request_trajectory(make_trajectory(got), at_ns)
        logic.on_reference(stamp, x, v)
        assert logic.on_position(stamp, x, k * 1e-4) is not None
        if late < 0 and k == 249:
            # announced ahead: nothing changes before its stamp
            assert ctrl.mismatches == 0 and ctrl.diagnostics()['ff_active'] == 1.0
    assert switch_k == 250
    # a late announcement: the samples stepped with the old copy are one mismatch (the
    # feed-forward waits, off, for its next bind), and none after it
    assert ctrl.mismatches == (1 if late > 0 else 0)
    assert ctrl.diagnostics()['ff_active'] == 1.0
    assert ctrl.learned().period_s == 1 / 137.0
    assert ctrl.periods_learned >= 3


def test_a_bad_announcement_names_its_form():
    from piezo_stage_ros.nodes.logic import parse_trajectory
    with pytest.raises(ParameterError, match='trajectory announcement.*stamp_ns'):
        parse_trajectory('{"trajectory": {}}')
    with pytest.raises(ParameterError, match='sine.frequency_hz'):
        parse_trajectory('{"stamp_ns": 0, "trajectory": {"sine.frequency_hz": -1.0}}')


def test_a_trajectory_the_learning_cannot_take_leaves_the_loop_on_feedback():
    # a step has no period: a learning feed-forward cannot take it; the loop must go on (the
    # trajectory node plays it already), the reason reported, each sample fed back alone
    from piezo_stage_ros.core.control.feedforward import FeedForwardController
    from piezo_stage_ros.core.model.hysteresis import HysteresisParams, make_hysteresis
    from piezo_stage_ros.core.model.stage import linear_plant
    params = ControllerParams().with_flat({'feedforward.mode': 'inverse_learning'})
    sine = make_trajectory(TrajectoryParams.from_flat({'kind': 'sine'}))
    step = make_trajectory(TrajectoryParams.from_flat({'kind': 'step'}))
    ctrl = build_controller(params, 1e-4, linear_plant(StageParams().plant),
                            make_hysteresis(HysteresisParams()))
    assert isinstance(ctrl, FeedForwardController)
    ctrl.bind(sine)
    reasons: list[str] = []
    # what is bound, and at which sample: a rebuild binds it from then on (not the refused
    # step, nor a line announced ahead before its stamp)
    bound: list[tuple[int, object]] = []
    logic = ControllerLogic(ctrl, on_refused=reasons.append,
                            on_bound=lambda t: bound.append((k, t)))
    refs = TrajectoryLogic(sine, sample_rate_hz=1e4)
    line = make_trajectory(TrajectoryParams.from_flat({'kind': 'sine',
                                                       'sine.frequency_hz': 137.0}))
    for k in range(300):
        if k == 100:
            refs.switch(step)
            logic.request_trajectory(step, 100 * 100_000)
        if k == 200:
            logic.request_trajectory(line, 250 * 100_000)  # announced ahead of its stamp
        if k == 250:
            refs.switch(line)
        x, v = refs.on_position(k * 100_000)
        logic.on_reference(k * 100_000, x, v)
        command = logic.on_position(k * 100_000, x, k * 1e-4)
        assert command is not None and np.isfinite(command.voltage_v)
    assert len(reasons) == 1 and 'learning needs a periodic reference' in reasons[0]
    assert ctrl.mismatches > 0
    assert bound == [(250, line)]
    assert ctrl.diagnostics()['ff_active'] == 1.0 and ctrl.period_s == 1 / 137.0
