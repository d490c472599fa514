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

"""The wire contract (core/contracts/wire.py): topics, stamps and the one diagnostics order."""

import ast
import math
from pathlib import Path

import numpy as np
from piezo_stage_ros.core.contracts import wire
from piezo_stage_ros.core.contracts.errors import BagError
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.loop.closed_loop import run
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.stage import Stage, StageParams
from piezo_stage_ros.nodes.logic import ControllerLogic
import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_node_topics_resolve_to_the_bag_topics_under_the_root_namespace():
    bag = wire.topic_names(wire.DEFAULT_NAMESPACE)
    for key, msgtype in wire.BAG_TOPICS.items():
        relative = f'{wire.STAGE}/{key}'
        assert '/' + relative == bag[key]
        assert wire.TOPIC_TYPES[relative] == msgtype
    assert (wire.POSITION, wire.REFERENCE, wire.COMMAND, wire.DIAGNOSTICS, wire.APPLIED,
            wire.TRUE_POSITION) == tuple(f'{wire.STAGE}/{key}' for key in wire.BAG_TOPICS)
    assert all(not t.startswith('/') for t in wire.TOPIC_TYPES if t != wire.CLOCK)
    # the recorder takes what the nodes publish: every topic but the clock and the ones only a
    # simulation knows (the offline runner writes those into its bags)
    simulated = {f'{wire.STAGE}/{key}' for key in wire.SIMULATION_TOPICS}
    assert simulated < set(wire.TOPIC_TYPES)
    assert set(wire.RECORDED_TOPICS) == set(wire.TOPIC_TYPES) - {wire.CLOCK} - simulated
    assert set(wire.REQUIRED_TOPICS) < set(wire.BAG_TOPICS)


@pytest.mark.parametrize('namespace, expected', [
    ('/stage', '/stage/position'), ('stage/', '/stage/position'), ('/', '/position'),
    ('', '/position'), ('/robot1/stage', '/robot1/stage/position')])
def test_topic_names_under_a_namespace(namespace, expected):
    assert wire.topic_names(namespace)['position'] == expected


@pytest.mark.parametrize('namespace', ['/1stage', '/st-age', '//stage'])
def test_bad_namespace_is_refused(namespace):
    with pytest.raises(BagError, match='not a valid ROS namespace'):
        wire.normalize_namespace(namespace)


def test_launch_file_takes_the_recorded_topics_from_the_contract():
    source = (ROOT / 'launch' / 'closed_loop.launch.py').read_text(encoding='utf8')
    tree = ast.parse(source)
    imported = {alias.name for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
                and node.module == 'piezo_stage_ros.core.contracts.wire' for alias in node.names}
    assert 'RECORDED_TOPICS' in imported
    literals = [node.value for node in ast.walk(tree)
                if isinstance(node, ast.Constant) and isinstance(node.value, str)]
    assert not [text for text in literals if text.startswith(wire.STAGE + '/')]


@pytest.mark.parametrize('stamp_ns', [0, 1, 999_999_999, 1_000_000_000, 1_600_000_000_123_456_789])
def test_stamps_round_trip_in_integer_nanoseconds(stamp_ns):
    sec, nanosec = wire.ns_to_stamp(stamp_ns)
    assert 0 <= nanosec < wire.NS_PER_S
    assert wire.stamp_to_ns(sec, nanosec) == stamp_ns
    assert wire.ns_to_stamp(1_500_000_123) == (1, 500_000_123)


# --- the one diagnostics order ------------------------------------------------------------
#
# The offline loop used to keep a mapping-only controller's insertion order and the controller
# node sorted the names, while the bag writer has always stored them sorted: one reader now
# gives the sorted order to all three.

class _PairController:
    """Offers the cheap names/values pair, declared in an unsorted order."""

    diagnostic_names = ('theta', 'alpha', 'mid')
    sample_time_s = 1e-4

    def __init__(self):
        self.k = 0

    def diagnostic_values(self):
        return (1.0 + self.k, 2.0 + self.k, 3.0 + self.k)

    def diagnostics(self):
        return dict(zip(self.diagnostic_names, self.diagnostic_values()))

    def reset(self, position_m, reference_m):
        self.k = 0

    def step(self, position_m, reference_m, reference_velocity_mps):
        self.k += 1
        return 0.0


class _MappingController(_PairController):
    """Offers only the mapping, built in an unsorted insertion order."""

    diagnostic_names = None

    def diagnostics(self):
        return {'theta': 1.0 + self.k, 'alpha': 2.0 + self.k, 'mid': 3.0 + self.k}


@pytest.mark.parametrize('cls', [_PairController, _MappingController])
def test_every_reader_gives_the_sorted_order(cls):
    ctrl = cls()
    names, read = wire.diagnostic_reader(ctrl)
    assert names == ('alpha', 'mid', 'theta')
    ctrl.k = 5
    assert tuple(read()) == (7.0, 8.0, 6.0)
    logic = ControllerLogic(cls(), mode='lockstep', diagnostics_every=1)
    assert logic.names == names
    logic.on_position(0, 0.0, 0.0)
    out = logic.on_reference(0, 0.0, 0.0)
    assert out is not None and tuple(out.diagnostics) == (3.0, 4.0, 2.0)
    record = run(Stage(StageParams()), cls(), make_trajectory(TrajectoryParams()),
                 duration_s=3e-4, diagnostics_every=1)
    assert tuple(record.diagnostics) == names
    np.testing.assert_array_equal(record.diagnostics['theta'], [2.0, 3.0, 4.0])


@pytest.mark.parametrize('names', [('only',), ('b', 'a')])
def test_small_pairs_read_as_sequences(names):
    class One(_PairController):
        diagnostic_names = names

        def diagnostic_values(self):
            return tuple(float(i) for i in range(len(names)))
    keys, read = wire.diagnostic_reader(One())
    assert keys == tuple(sorted(names))
    assert [dict(zip(keys, read()))[n] for n in names] == [float(i) for i in range(len(names))]


def test_mapping_that_loses_a_key_reads_nan():
    class Shrinking(_MappingController):
        def diagnostics(self):
            return {'theta': 1.0} if self.k else {'theta': 1.0, 'alpha': 2.0}
    ctrl = Shrinking()
    names, read = wire.diagnostic_reader(ctrl)
    ctrl.k = 1
    values = read()
    assert names == ('alpha', 'theta') and math.isnan(values[0]) and values[1] == 1.0


@pytest.mark.parametrize('kind', ['rac', 'pi'])
def test_offline_loop_node_and_bag_carry_the_same_columns(kind, tmp_path):
    stage = Stage(StageParams())
    traj = make_trajectory(TrajectoryParams())
    record = run(stage, build_controller(ControllerParams(type=kind), 1e-4), traj, duration_s=0.01,
                 diagnostics_every=1)
    logic = ControllerLogic(build_controller(ControllerParams(type=kind), 1e-4))
    assert tuple(record.diagnostics) == logic.names == tuple(sorted(logic.names))
    bagwrite = pytest.importorskip('piezo_stage_ros.analysis.bagwrite',
                                   reason='rosbags writes bags')
    from piezo_stage_ros.analysis.bagread import read_topics
    bagwrite.write_run(record, tmp_path / 'run')
    _, _, _, names = read_topics(tmp_path / 'run')
    assert names['diagnostics'] == logic.names
    assert np.isfinite(record.diagnostics[logic.names[0]]).all()
