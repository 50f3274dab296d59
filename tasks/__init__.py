"""Pure processing stages on numpy arrays: no Prefect, no zarr, no file paths."""

# pymeshlab first, before Open3D and scipy.spatial load their own C++ runtimes. With all three
# loaded, a process sometimes corrupts its heap when it exits, after its work is done (glibc aborts
# with "malloc_consolidate(): unaligned fastbin chunk detected"): measured in Dask worker processes,
# 3 of 18 exits in the other order, about 1 in 6 in this one. Not solved; loading pymeshlab only
# when meshing made the main process abort at exit instead.
import pymeshlab  # noqa: F401  (isort: skip)

# One BLAS thread in every process that runs a stage, whatever the machine's core count or the
# caller's OPENBLAS_NUM_THREADS: OpenBLAS splits its products over its threads in ways that change
# the rounding, so scipy's least_squares found other pass poses (13th digit) with 1 thread (a Dask
# worker) than with 2 (a 2-core process), and every byte downstream of the registration differed.
# The stages run per pass in parallel instead. Only libraries loaded by now are held: numpy's and
# scipy's OpenBLAS, loaded here on purpose.
import numpy  # noqa: E402,F401  (isort: skip)
import scipy.linalg  # noqa: E402,F401  (isort: skip)
import scipy.optimize  # noqa: E402,F401  (isort: skip)
from threadpoolctl import threadpool_limits  # noqa: E402  (isort: skip)

threadpool_limits(limits=1, user_api="blas")
