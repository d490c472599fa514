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
Print one line: numpy/scipy versions, each loaded BLAS (version, kernel in use, threads), SIMD.

`make test-matrix` prints it before each run, so the test-matrix table in docs/results.md shows
whether an OPENBLAS_CORETYPE or NPY_DISABLE_CPU_FEATURES setting really took effect (not a test
module: pytest collects ``test_*.py`` only).
"""

from pathlib import Path

import numpy as np
import scipy
import scipy.linalg  # noqa: F401  (loads scipy's own OpenBLAS)
from threadpoolctl import threadpool_info


def main() -> None:
    # one entry per OpenBLAS loaded (numpy's and scipy's wheels each carry their own)
    blas = [f"{Path(i['filepath']).name.split('.so')[0].split('-')[0]} {i.get('version')} "
            f"{i.get('architecture')} x{i['num_threads']}"
            for i in threadpool_info() if i['user_api'] == 'blas']
    try:  # numpy >= 2 keeps the dispatch table in numpy._core
        from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    except ImportError:
        from numpy.core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    # numpy's own SIMD kernels (sin, exp, sums...): the highest dispatch target that is on
    simd = [name for name in __cpu_dispatch__ if __cpu_features__.get(name)][-1:] or ['baseline']
    print(f'numpy {np.__version__}, scipy {scipy.__version__}: ' + ', '.join(sorted(blas))
          + f'; numpy SIMD {simd[0]}')

if __name__ == '__main__':
    main()
