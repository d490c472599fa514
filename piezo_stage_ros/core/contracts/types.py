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


"""The array types of the package's signatures, named once."""

from __future__ import annotations

from typing import TypeAlias

import numpy as np
from numpy.typing import NDArray

__all__ = ['BoolArray', 'ByteMatrix', 'ComplexArray', 'FloatArray', 'IntArray']

#: A float64 array: samples, coefficients, frequencies (units in each signature's docstring).
FloatArray: TypeAlias = NDArray[np.float64]
#: An int64 array: nanosecond stamps, counts, indices.
IntArray: TypeAlias = NDArray[np.int64]
#: Rows of raw bytes: one serialized message per row.
ByteMatrix: TypeAlias = NDArray[np.uint8]
#: A boolean array: masks over samples or rows.
BoolArray: TypeAlias = NDArray[np.bool_]
#: A complex128 array: poles, zeros, frequency responses.
ComplexArray: TypeAlias = NDArray[np.complex128]
