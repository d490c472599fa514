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

"""Parameters given to a node that it does not declare: sources, hints, refusal (no rclpy)."""

from __future__ import annotations

from pathlib import Path

from piezo_stage_ros.core.config.loader import controller_table, plant_table
from piezo_stage_ros.core.config.unknown import (
    check_given,
    ros_sources,
    unknown_given,
)
from piezo_stage_ros.core.contracts.errors import ConfigError, ParameterError
from piezo_stage_ros.core.control.stability import StabilityParams
from piezo_stage_ros.nodes.tables import design_model
import pytest

CONFIG = Path(__file__).resolve().parents[1] / 'config'
CONTROLLER = {spec.name for spec in controller_table().specs()}
PLANT = {spec.name for spec in plant_table().specs()}


def test_a_typo_in_an_override_is_named_with_its_source_and_the_closest_name():
    argv = ['controller_node', '--ros-args', '-p', 'rac.gama:=100']
    sources = ros_sources(argv)
    [msg] = unknown_given('controller_node', ['rac.gama'], CONTROLLER, sources)
    assert "'rac.gama'" in msg and 'controller_node' in msg
    assert '-p rac.gama:=100' in msg and "did you mean 'rac.gamma'?" in msg
    with pytest.raises(ConfigError, match="did you mean 'rac.gamma'"):
        check_given('controller_node', ['rac.gama'], CONTROLLER, sources)


def test_declared_names_and_the_ones_ros_reads_itself_pass():
    given = ['rac.gamma', 'use_sim_time', 'qos_overrides./stage/position.publisher.depth']
    assert unknown_given('controller_node', given, CONTROLLER) == []
    check_given('controller_node', given, CONTROLLER)


def test_a_file_section_is_named_and_a_node_prefixed_override_is_for_that_node(tmp_path):
    path = tmp_path / 'bad.yaml'
    path.write_text('/**:\n  ros__parameters:\n    sample_rate_hz: 10000.0\n'
                    'controller_node:\n  ros__parameters:\n    rac:\n      gama: 1.0\n')
    argv = ['x', '--ros-args', '--params-file', str(path), '-p', 'plant_node:sed:=3', '--',
            '-p', 'not_ros:=1']
    sources = ros_sources(argv)
    assert [s.node for s in sources] == ['/**', 'controller_node', 'plant_node']
    [msg] = unknown_given('controller_node', ['rac.gama'], CONTROLLER, sources)
    assert f"{path}, section 'controller_node'" in msg
    [msg] = unknown_given('plant_node', ['sed'], PLANT, sources)
    assert '-p plant_node:sed:=3' in msg and "did you mean 'seed'?" in msg


def test_a_value_for_every_node_is_kept_when_another_node_of_the_process_declares_it():
    sources = ros_sources(['stage_servo', '--ros-args', '-p', 'seed:=4'])
    assert unknown_given('controller_node', ['seed'], CONTROLLER, sources, others=PLANT) == []
    # addressed to this node by name: refused even though another node declares it
    sources = ros_sources(['stage_servo', '--ros-args', '-p', 'controller_node:seed:=4'])
    assert unknown_given('controller_node', ['seed'], CONTROLLER, sources, others=PLANT)
    # a name no node of the process declares is refused on each node it was given to
    assert unknown_given('controller_node', ['sead'], CONTROLLER, sources, others=PLANT)


def test_the_multi_axis_file_points_to_the_offline_runner():
    argv = ['plant_node', '--ros-args', '--params-file', str(CONFIG / 'default.yaml'),
            '--params-file', str(CONFIG / 'xy_stage.yaml')]
    sources = ros_sources(argv)
    given = ['seed', 'axes.names', 'axes.x.seed', 'axes.coupling.gain']
    [msg] = unknown_given('plant_node', given, PLANT, sources)
    assert "'axes.names'" in msg and 'xy_stage.yaml' in msg
    assert 'multi-axis' in msg and 'simulate --config FILE' in msg and 'did you mean' not in msg


def test_a_name_from_no_known_source_still_is_refused():
    [msg] = unknown_given('trajectory_node', ['kindd'], {'kind'}, [])
    assert 'from its parameter overrides' in msg and "did you mean 'kind'?" in msg


def test_a_misspelt_key_in_a_file_section_gets_the_closest_name_too():
    with pytest.raises(ParameterError, match="'rac.gama' = 1.0 is not a parameter of this node.*"
                                             "did you mean 'rac.gamma'"):
        controller_table().build({'rac.gama': 1.0})


def test_the_controller_nodes_reading_of_its_files_names_them(tmp_path):
    path = tmp_path / 'typo.yaml'
    path.write_text('plant_node:\n  ros__parameters:\n    plant:\n      modle: reduced\n')
    with pytest.raises(ParameterError,
                       match=f"'plant.modle' = 'reduced' .*did you mean 'plant.model'.*{path}"):
        design_model(StabilityParams().replace(design_model='plant'), [str(path)])


def test_an_unknown_top_level_name_is_refused_offline_as_the_node_refuses_it(tmp_path):
    # 'sed' is under no group of the table: the offline loader refuses it as the node does,
    # naming it, the closest name and the top-level names the node knows.
    from piezo_stage_ros.core.config.loader import load_loop_config, OTHER_HEADS
    path = tmp_path / 'sed.yaml'
    path.write_text('plant_node:\n  ros__parameters:\n    sed: 3\n')
    with pytest.raises(ParameterError) as info:
        load_loop_config([CONFIG / 'default.yaml', path])
    msg = str(info.value)
    assert "'plant_node sed' = 3 is not a parameter of this node" in msg
    assert "did you mean 'seed'?" in msg
    heads = dict.fromkeys(spec.name.split('.', 1)[0] for spec in plant_table().specs())
    assert 'top-level keys of plant_node: ' + ', '.join(list(heads) + list(OTHER_HEADS)) in msg
    # the node's own refusal of the same name, for comparison
    [node] = unknown_given('plant_node', ['sed'], PLANT, ros_sources(
        ['plant_node', '--ros-args', '--params-file', str(path)]))
    assert "'sed'" in node and "did you mean 'seed'?" in node


@pytest.mark.parametrize('text', [
    'controller_node:\n  ros__parameters:\n    use_sim_time: true\n',
    'trajectory_node:\n  ros__parameters:\n    qos_overrides:\n      /x:\n        depth: 5\n',
    '/**:\n  ros__parameters:\n    other_nodes_name: 1\n',
    'stage_servo:\n  ros__parameters:\n    anything: 1\n',
])
def test_what_rclpy_or_other_nodes_read_is_still_accepted_offline(tmp_path, text):
    from piezo_stage_ros.core.config.loader import load_loop_config
    path = tmp_path / 'ok.yaml'
    path.write_text(text)
    load_loop_config([CONFIG / 'default.yaml', path])


@pytest.mark.parametrize('node, name', [
    ('controller_node', 'axes.x.pi.k_p'),  # a per-axis value in a file of one axis
    ('plant_node', 'scan.kind'),  # the scan is the trajectory node's, and of several axes
    ('trajectory_node', 'scan.kind'),  # one axis: no scan over axes to read it
])
def test_names_of_several_axes_are_refused_where_no_node_reads_them(tmp_path, node, name):
    # the one-axis nodes declare no axes.* or scan.*, and refuse them; offline they were
    # accepted and left unread
    from piezo_stage_ros.core.config.loader import load_loop_config
    path = tmp_path / 'one_axis.yaml'
    path.write_text(f'{node}:\n  ros__parameters:\n    {name}: 5\n')
    with pytest.raises(ParameterError, match=f"'{node} {name}' = 5 is not a parameter"):
        load_loop_config([CONFIG / 'default.yaml', path])


def test_names_of_several_axes_are_read_in_a_file_of_several_axes(tmp_path):
    from piezo_stage_ros.core.config.loader import load_loop_config
    path = tmp_path / 'scan.yaml'
    path.write_text('controller_node:\n  ros__parameters:\n    axes.x.pi.k_p: 5.0\n')
    load_loop_config([CONFIG / 'xy_stage.yaml', path])
    path.write_text('plant_node:\n  ros__parameters:\n    scan.kind: raster\n')
    with pytest.raises(ParameterError, match="'plant_node scan.kind' = 'raster' is not a"):
        load_loop_config([CONFIG / 'xy_stage.yaml', path])
