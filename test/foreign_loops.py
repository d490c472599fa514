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
Bags of closed-loop runs under loops the package did not write, as a lab's recorder writes them.

:func:`write_plain_bag` stores a run with rosbags' plain ``Writer`` on the package's topics
(``/stage/position``, ``/stage/reference``, ``/stage/command``), one message per sample, with
receive-like log times and no run description in the bag (a lab's bag has none).
:func:`foreign_case` simulates a stage of the family under one of the foreign loops
(:mod:`piezo_stage_ros.core.identification.foreign`) and writes its two runs.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from piezo_stage_ros.core.contracts import wire
from piezo_stage_ros.core.identification.foreign import foreign_runs, ForeignLoopParams
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.model.family import member_params, sample_family
from piezo_stage_ros.core.model.stage import StageParams
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores

STORE = get_typestore(Stores.ROS2_JAZZY)
#: Stamps of a lab's recording: seconds since the epoch.
EPOCH_S = 1_700_000_000


def write_plain_bag(record: RunRecord, path: Path) -> Path:
    """Write ``record`` with rosbags' plain Writer on the package's topics; return the path."""
    js = STORE.types['sensor_msgs/msg/JointState']
    hdr = STORE.types['std_msgs/msg/Header']
    stamp_t = STORE.types['builtin_interfaces/msg/Time']
    f64 = STORE.types['std_msgs/msg/Float64']
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {key: writer.add_connection(f'/stage/{key}', wire.BAG_TOPICS[key],
                                            typestore=STORE)
                 for key in ('position', 'reference', 'command')}
        for k in range(len(record)):
            ns = EPOCH_S * 1_000_000_000 + int(round(float(record.time_s[k]) * 1e9))
            header = hdr(stamp=stamp_t(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000),
                         frame_id='')
            pos = js(header=header, name=['stage'],
                     position=np.array([record.position_m[k]]), velocity=np.zeros(0),
                     effort=np.zeros(0))
            ref = js(header=header, name=['stage'],
                     position=np.array([record.reference_m[k]]),
                     velocity=np.array([record.reference_velocity_mps[k]]), effort=np.zeros(0))
            # log times a little after the stamps, as a recorder receives them
            writer.write(conns['position'], ns + 20_000,
                         STORE.serialize_cdr(pos, 'sensor_msgs/msg/JointState'))
            writer.write(conns['reference'], ns + 25_000,
                         STORE.serialize_cdr(ref, 'sensor_msgs/msg/JointState'))
            writer.write(conns['command'], ns + 40_000,
                         STORE.serialize_cdr(f64(data=float(record.command_v[k])),
                                             'std_msgs/msg/Float64'))
    return path


def foreign_stage(index: int, seed: int, noise_m: float) -> StageParams:
    """Return the ``index``-th random member of the family drawn with ``seed``, with noise."""
    member = sample_family(index + 1, seed)[index]
    return member_params(StageParams(), member).with_flat(
        {'chain.sensor_noise_std_m': noise_m, 'seed': seed * 1000 + index})


def foreign_case(folder: Path, stage: StageParams, loop: ForeignLoopParams,
                 **meta: Any) -> tuple[Path, Path, dict[str, RunRecord]]:
    """Simulate ``stage`` under ``loop``; write its excitation and sine runs as plain bags."""
    runs = foreign_runs(stage, loop, meta=meta)
    folder.mkdir(parents=True, exist_ok=True)
    return (write_plain_bag(runs['excite'], folder / 'cl_excite'),
            write_plain_bag(runs['sine'], folder / 'cl_sine'), runs)
