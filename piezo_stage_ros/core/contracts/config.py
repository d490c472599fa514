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
Loading ROS 2 parameter YAML files for the offline runner and the tools.

The files in ``config/`` are ordinary ROS 2 parameter files, usable with
``ros2 run ... --ros-args --params-file FILE`` and in launch files::

    /**:
      ros__parameters:
        sample_rate_hz: 10000.0
    plant_node:
      ros__parameters:
        plant:
          model: third_order

Nested mappings become dotted names (``plant.model``), as ROS 2 does. This module only maps a file
onto flat per-node dictionaries; each parameter group validates itself with
:meth:`piezo_stage_ros.core.contracts.params.Params.from_flat`, so no module here knows any
parameter.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import os
from pathlib import Path
import re
import sys
from typing import Any, Iterable, Mapping

from piezo_stage_ros.core.contracts.errors import ConfigError
import yaml

__all__ = ['Config', 'find_config', 'flatten', 'load_config', 'nest']

WILDCARD = '/**'
PACKAGE = 'piezo_stage_ros'


class _RosYamlLoader(yaml.SafeLoader):
    """
    A safe YAML loader that reads ``1e-6`` as a float, as ROS 2 (yaml-cpp) does.

    PyYAML follows YAML 1.1, where a float needs a dot (``1.0e-6``); a parameter file written for
    ROS would otherwise give the string ``'1e-6'``.
    """


_RosYamlLoader.add_implicit_resolver(
    'tag:yaml.org,2002:float',
    re.compile(r"""^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"""),
    list('-+0123456789'))


def flatten(mapping: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    """
    Flatten nested mappings into dotted names, as ROS 2 does for parameter files.

    Parameters
    ----------
    mapping : Mapping
        Nested parameter values.
    prefix : str
        Prepended to every name.

    Returns
    -------
    dict
        ``{'a.b': value}`` for ``{'a': {'b': value}}``.

    """
    out: dict[str, Any] = {}
    for key, value in mapping.items():
        name = f'{prefix}{key}'
        if isinstance(value, Mapping):
            out.update(flatten(value, name + '.'))
        else:
            out[name] = value
    return out


def nest(flat: Mapping[str, Any]) -> dict[str, Any]:
    """Turn dotted names into nested mappings, as a ROS 2 parameter file holds them."""
    out: dict[str, Any] = {}
    for name, value in flat.items():
        node = out
        parts = name.split('.')
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out


def _node_key(section: str) -> str:
    """Return ``'plant_node'`` for ``'/ns/plant_node'``, and ``'/**'`` for any wildcard."""
    if section.strip('/') in ('**', '*'):
        return WILDCARD
    return section.rstrip('/').rsplit('/', 1)[-1]


@dataclass(frozen=True)
class Config:
    """
    Parameters of every node, read from one or more ROS 2 parameter files.

    Attributes
    ----------
    sources : tuple of Path
        Files read, in order (later files override earlier ones).
    sections : dict
        ``{node name or '/**': {dotted name: value}}``.

    """

    sources: tuple[Path, ...] = ()
    sections: dict[str, dict[str, Any]] = field(default_factory=dict)

    def node(self, name: str) -> dict[str, Any]:
        """
        Return the flat parameters of node ``name``, wildcard ``/**`` values included.

        Parameters
        ----------
        name : str
            Node name, e.g. ``'controller_node'``.

        Returns
        -------
        dict
            ``{dotted name: value}``; node-specific values override wildcard ones.

        """
        merged = dict(self.sections.get(WILDCARD, {}))
        merged.update(self.sections.get(name, {}))
        return merged

    def with_overrides(self, name: str, values: Mapping[str, Any]) -> Config:
        """Return a copy with ``values`` set in the section of node ``name``."""
        sections = {k: dict(v) for k, v in self.sections.items()}
        sections.setdefault(name, {}).update(values)
        return Config(self.sources, sections)


def load_config(paths: Iterable[str | os.PathLike[str]]) -> Config:
    """
    Read ROS 2 parameter files into one :class:`Config`.

    Parameters
    ----------
    paths : iterable of path-like
        Files, read in order; a later file overrides values of an earlier one.

    Returns
    -------
    Config

    Raises
    ------
    ConfigError
        If a file is missing, is not YAML, or is not shaped ``<node>: ros__parameters: {...}``;
        the message names the file and what is wrong.

    """
    sources: list[Path] = []
    sections: dict[str, dict[str, Any]] = {}
    for raw in paths:
        path = Path(raw)
        try:
            text = path.read_text(encoding='utf-8')
        except OSError as exc:
            raise ConfigError(f'{path}: cannot read parameter file ({exc.strerror})') from None
        try:
            doc = yaml.load(text, Loader=_RosYamlLoader)  # noqa: S506 (a SafeLoader)
        except yaml.YAMLError as exc:
            raise ConfigError(f'{path}: not valid YAML ({exc})') from None
        if doc is None:
            doc = {}
        if not isinstance(doc, dict):
            raise ConfigError(f'{path}: expected a mapping of node names, '
                              f'got {type(doc).__name__}')
        for section, body in doc.items():
            if not isinstance(body, dict) or set(body) != {'ros__parameters'} or \
                    not isinstance(body['ros__parameters'], dict):
                raise ConfigError(f'{path}: section {section!r} must contain exactly '
                                  "'ros__parameters:' with a mapping of parameters")
            key = _node_key(str(section))
            sections.setdefault(key, {}).update(flatten(body['ros__parameters']))
        sources.append(path)
    return Config(tuple(sources), sections)


def find_config(name: str = 'default.yaml') -> Path:
    """
    Locate a configuration file shipped with the package.

    Looks, in order, in the source tree (``config/`` beside the package), in
    ``<sys.prefix>/share/piezo_stage_ros/config`` (pip or virtualenv install) and in every
    ``share/piezo_stage_ros/config`` of ``AMENT_PREFIX_PATH`` (a colcon install). A name that is
    an existing path is returned as it is.

    Parameters
    ----------
    name : str
        File name (``'default.yaml'``, ``'table3_rac.yaml'`` ...) or a path.

    Returns
    -------
    Path

    Raises
    ------
    ConfigError
        If no such file exists; the message lists where it looked.

    """
    given = Path(name)
    if given.is_file():
        return given
    roots = [Path(__file__).resolve().parents[3] / 'config',
             Path(sys.prefix) / 'share' / PACKAGE / 'config']
    roots += [Path(p) / 'share' / PACKAGE / 'config'
              for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    for root in roots:
        if (root / name).is_file():
            return root / name
    raise ConfigError(f'configuration {name!r} not found; looked in: '
                      + ', '.join(str(r) for r in roots))
