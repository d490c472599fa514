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
The three nodes in one process on one ``rclpy.experimental.EventsExecutor``.

Across processes one message hop costs about 100 us on loopback, which caps a lockstep loop
near real time at 10 kHz; within one process it costs about 12 us. ``stage_servo`` runs the
plant, controller and trajectory node classes together (each keeps its own name, parameters and
topics, so the same parameter file and the same graph result). ``--nodes`` runs a subset, e.g.
``--nodes controller,trajectory`` beside a plant in another process.

Run: ``ros2 run piezo_stage_ros stage_servo --ros-args --params-file default.yaml``.
"""

from __future__ import annotations

from typing import Sequence

from piezo_stage_ros.core.config.loader import load_loop_config, LoopConfig
from piezo_stage_ros.core.contracts.errors import PiezoStageError
from piezo_stage_ros.nodes.controller_node import ControllerNode
from piezo_stage_ros.nodes.controller_node import factory as controller_factory
from piezo_stage_ros.nodes.logic import Command, Sample
from piezo_stage_ros.nodes.plant_node import PlantNode
from piezo_stage_ros.nodes.recording import backlog_samples
from piezo_stage_ros.nodes.runner import run
from piezo_stage_ros.nodes.servo import ServoProcess, ServoSample
from piezo_stage_ros.nodes.trajectory_node import TrajectoryNode

__all__ = ['bind_what_plays', 'connect_direct', 'main']


def connect_direct(plant: PlantNode, controller: ControllerNode,
                   trajectory: TrajectoryNode) -> None:
    """
    Hand each sample from node to node by call (``--direct``), in the order of one sample.

    y_k goes to the trajectory node, (y_k, x_d, x_d') to the controller node, u_k back to the
    plant: the loop of :mod:`piezo_stage_ros.core.contracts.interfaces`, without serializing
    anything the three nodes exchange among themselves. The topics are still published for any
    outside subscriber (a recorder, ``ros2 topic echo``); parameters and services work as ever,
    served between batches of samples. In real time the plant's servo loop (``nodes/servo.py``)
    calls the trajectory's and the controller's logic in its own thread, paced by its own clock.
    """
    controller.attach_direct()
    trajectory.attach_direct()

    def check() -> str | None:
        # the plant's configure checks the controller it will run, with the gains as they are
        params, stability, _ = controller.binding.objects
        try:
            controller._check(params, stability)
        except PiezoStageError as exc:
            return str(exc)
        return None

    plant.check = check
    # the goals: checked against the plant's own stage; a feed-forward binds their reference
    trajectory.set_stage(plant.binding.objects[0])
    trajectory.follow_plant(plant.state, plant.on_state)
    trajectory.logic.on_reference_change = controller.logic.request_trajectory
    if plant.opts.mode == 'lockstep' or not plant.opts.servo.process:
        # these logic objects run the loop (a servo process builds both from one trajectory)
        bind_what_plays(controller, trajectory)
    if plant.opts.mode != 'lockstep':
        # real time: the plant's servo thread runs trajectory and controller for each sample;
        # the executor publishes what they computed, in batches, for outside subscribers
        def publish(batch: list[ServoSample]) -> None:
            for s in batch:
                trajectory.publish(s.stamp_ns, s.reference_m, s.velocity_mps)
                controller.publish(Command(s.stamp_ns, s.command_v, s.diagnostics,
                                           s.diagnostic_names))

        process = None
        if plant.opts.servo.process:
            # the servo loop in a process of its own (no interpreter lock shared with this
            # executor), on copies of the logic built from the same parameters; the peer
            # nodes forward their parameter changes to it
            stage, plant_opts = plant.binding.objects
            params, stability, controller_opts = controller.binding.objects
            traj_params, traj_opts = trajectory.binding.objects
            loop = LoopConfig(stage=stage, plant_node=plant_opts, controller=params,
                              stability=stability, controller_node=controller_opts,
                              trajectory=traj_params, trajectory_node=traj_opts)
            process = ServoProcess(loop, plant_opts.duration_s,
                                   capacity=backlog_samples(plant_opts.recording,
                                                            stage.sample_rate_hz),
                                   design_plant=controller.design_plant)
            controller.forward = trajectory.forward = process.change
            trajectory.goal_events = process.take_goal_events
            trajectory.loop_index = lambda: process.index
        plant.attach_servo(trajectory.logic, controller.logic, publish, process)
        return

    def step(sample: Sample) -> float:
        ref, vel = trajectory.answer(sample.stamp_ns, sample.position_m)
        return controller.answer(sample.stamp_ns, sample.position_m, ref, vel)

    plant.attach_direct(step)


def bind_what_plays(controller: ControllerNode, trajectory: TrajectoryNode) -> None:
    """
    Bind the controller's feed-forward to the trajectory the trajectory node plays.

    A controller node reads the trajectory its feed-forward predicts from its parameter files
    (a node in another process has nothing else); the trajectory node plays its own
    parameters, overrides included. Where the two differ, the composed controller binds the
    trajectory node's trajectory at the first sample, by call, as it binds every later one:
    otherwise its feed-forward finds each reference mismatched and leaves it to the feedback.
    Nothing happens where they agree (one file for both nodes, as the launch files give).
    """
    if controller._ff_context is None:
        return  # no feed-forward: nothing reads the trajectory ahead
    configured = load_loop_config(controller._files).trajectory
    if configured != trajectory.binding.objects[0]:
        controller.logic.request_trajectory(trajectory.logic.trajectory)


def main(args: Sequence[str] | None = None) -> int:
    """Run the composed nodes (console script ``stage_servo``)."""
    return run('stage_servo', [('plant', PlantNode), ('controller', controller_factory(args)),
                               ('trajectory', TrajectoryNode)], args,
               'Plant, controller and trajectory nodes of piezo_stage_ros in one process.',
               connect=connect_direct)


if __name__ == '__main__':
    raise SystemExit(main())
