"""Settings shared by the compiled (Numba) kernels of ``tasks``.

Numba's OpenMP threading layer: the per-pass stages call kernels from several Python threads at
once (Prefect's thread pool), which the OpenMP layer allows and the default search would try TBB
first (too old here, with a warning on every start). Every kernel writes each output element from
one thread only, so results are the same bytes for any thread count.
"""

from __future__ import annotations

import numba

__all__ = ["numba"]

numba.config.THREADING_LAYER = "omp"
