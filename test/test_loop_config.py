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


"""One loader for every consumer: the same parameter file means the same thing everywhere."""

from __future__ import annotations

import argparse
from pathlib import Path

from piezo_stage_ros import cli, identify, simulate, soak
from piezo_stage_ros.core.config.loader import (
    find_config,
    load_config,
    load_loop_config,
    LoopConfig,
)
from piezo_stage_ros.core.contracts.errors import ConfigError, ParameterError
from piezo_stage_ros.core.control.controllers import ControllerParams
from piezo_stage_ros.core.loop.trajectories import TrajectoryParams
from piezo_stage_ros.core.model.stage import PlantParams
from piezo_stage_ros.hardware.emulator import main as emulator_main
from piezo_stage_ros.nodes.tables import design_model, params_files
import pytest

DEFAULT = find_config('default.yaml')
PI = find_config('table3_pi.yaml')


def _file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / 'extra.yaml'
    path.write_text(text, encoding='utf-8')
    return path


REALTIME = 'plant_node:\n  ros__parameters:\n    mode: realtime\n    backend: udp\n'
BAD_MODE = 'plant_node:\n  ros__parameters:\n    mode: realtim\n'


def test_default_files_give_the_default_objects() -> None:
    loop = load_loop_config([DEFAULT])
    assert loop == LoopConfig(sources=(DEFAULT,))


def test_node_settings_are_validated_and_noted_offline(tmp_path: Path) -> None:
    loop = load_loop_config([DEFAULT, _file(tmp_path, REALTIME)])
    assert loop.plant_node.mode == 'realtime' and loop.plant_node.backend == 'udp'
    notes = loop.offline_notes()
    assert len(notes) == 2 and 'mode: realtime' in notes[0] and 'backend: udp' in notes[1]
    assert load_loop_config([DEFAULT]).offline_notes() == []
    with pytest.raises(ParameterError, match="'mode' = 'realtim'"):
        load_loop_config([DEFAULT, _file(tmp_path, BAD_MODE)])


def test_ros_names_are_left_to_ros_and_misspelt_group_names_refused(tmp_path: Path) -> None:
    ok = _file(tmp_path, '/**:\n  ros__parameters:\n    use_sim_time: true\n'
                         'controller_node:\n  ros__parameters:\n    qos_overrides.x: 1\n')
    assert load_loop_config([DEFAULT, ok]).controller == ControllerParams()
    bad = _file(tmp_path, 'controller_node:\n  ros__parameters:\n    rac:\n      epsilon: 1\n')
    with pytest.raises(ParameterError, match="'rac.epsilon'"):
        load_loop_config([DEFAULT, bad])


@pytest.mark.parametrize('command', ['simulate', 'identify', 'emulator'])
def test_every_offline_command_runs_a_realtime_file_with_a_note(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str) -> None:
    extra = str(_file(tmp_path, REALTIME))
    if command == 'simulate':
        assert simulate.main(['--config', extra, '--duration', '0.01', '--json']) == 0
    elif command == 'identify':
        # it reads the configuration, then stops on the missing bags, not on the mode
        assert identify.main(['--config', extra]) == 2
    else:
        assert emulator_main(['--config', extra, '--port', '0', '--idle-timeout-s', '0.01']) == 0
    err = capsys.readouterr().err
    assert 'note: plant_node mode: realtime applies to the ROS nodes' in err
    assert 'plant_node backend: udp applies to the ROS plant node' in err


@pytest.mark.parametrize('command', ['simulate', 'identify', 'emulator'])
def test_every_command_refuses_a_bad_node_setting(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str) -> None:
    extra = str(_file(tmp_path, BAD_MODE))
    if command == 'simulate':
        assert simulate.main(['--config', extra, '--duration', '0.01']) == 1
    elif command == 'identify':
        assert identify.main(['--config', extra]) == 1
    else:
        assert emulator_main(['--config', extra, '--port', '0']) == 2
    assert "'mode' = 'realtim'" in capsys.readouterr().err


def test_design_model_follows_the_plant_unless_own(tmp_path: Path) -> None:
    # as ros2 run reads them: default.yaml + table3_pi.yaml runs the reduced plant
    loop = load_loop_config([DEFAULT, PI])
    assert loop.stage.plant.model == 'reduced' and loop.design_plant == loop.stage.plant
    own = _file(tmp_path, 'controller_node:\n  ros__parameters:\n    stability:\n'
                          '      design_model: own\n      plant:\n        model: '
                          'electromechanical\n')
    loop = load_loop_config([DEFAULT, PI, own])
    assert loop.design_plant.model == 'electromechanical'


def test_a_lone_controller_node_takes_the_plant_from_its_parameter_files(
        tmp_path: Path) -> None:
    argv = ['controller_node', '--nodes', 'controller', '--ros-args', '--params-file',
            str(DEFAULT), '-p', 'type:=pi', '--params-file', str(PI), '--', '--params-file',
            'not-ros.yaml']
    files = params_files(argv)
    assert files == [str(DEFAULT), str(PI)]
    stability = load_loop_config(files).stability
    plant, source = design_model(stability, files)
    assert plant.model == 'reduced'
    assert "plant node's reduced model" in source and str(PI) in source
    plant, source = design_model(stability, [])
    assert plant == PlantParams() and 'no --params-file' in source
    own = stability.replace(design_model='own', plant=PlantParams(model='electromechanical'))
    plant, source = design_model(own, files)
    assert plant.model == 'electromechanical' and 'design_model: own' in source
    with pytest.raises(ConfigError, match='cannot read'):
        design_model(stability, [str(tmp_path / 'missing.yaml')])


def test_launch_and_commands_share_the_loader() -> None:
    # the merged file the launch writes holds /**/<node> sections; they map to the same nodes
    config = load_config([DEFAULT, PI])
    assert LoopConfig.from_config(config) == load_loop_config([DEFAULT, PI])


def test_command_line_choices_come_from_the_declarations() -> None:
    def choices_of(parser: argparse.ArgumentParser, flag: str) -> tuple[str, ...]:
        action = next(a for a in parser._actions if flag in a.option_strings)
        return tuple(action.choices or ())
    sim = simulate.build_parser()
    assert choices_of(sim, '--plant') == cli.choices(PlantParams, 'model')
    assert choices_of(sim, '--controller') == cli.choices(ControllerParams, 'type')
    assert choices_of(sim, '--trajectory') == cli.choices(TrajectoryParams, 'kind')
    assert choices_of(soak._parser(), '--trajectory') == cli.choices(TrajectoryParams, 'kind')
    with pytest.raises(ValueError, match='no choices|not a parameter'):
        cli.choices(PlantParams, 'substeps')


@pytest.mark.parametrize('raised, status, text', [
    (cli.UsageError('bad flag'), 2, 'prog: error: bad flag (see prog --help)'),
    (ParameterError('x', 3, '[0, 1]'), 1, "prog: error: parameter 'x' = 3"),
    (FileNotFoundError(2, 'No such file or directory', 'f.txt'), 1,
     'prog: error: f.txt: No such file or directory'),
    (BrokenPipeError(32, 'Broken pipe'), 1, 'prog: error: Broken pipe\n'),
    (KeyboardInterrupt(), 130, 'prog: error: interrupted'),
])
def test_one_mapping_of_errors_to_exit_status(capsys: pytest.CaptureFixture[str],
                                               raised: BaseException, status: int,
                                               text: str) -> None:
    def body(args: argparse.Namespace) -> int:
        raise raised
    assert cli.run_command('prog', cli.Parser(prog='prog'), body, []) == status
    assert capsys.readouterr().err.startswith(text)
    assert cli.run_command('prog', cli.Parser(prog='prog'), body, ['--nope']) == 2
