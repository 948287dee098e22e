"""What every test file shares: one BLAS, MKL and OpenMP thread per pytest-xdist worker."""

import os

# pytest-xdist runs one worker per core (pyproject.toml's addopts): each worker's numpy, MKL and OpenMP then
# use one thread, as the workflow's single-thread jobs do, instead of every worker starting one per core
if os.environ.get("PYTEST_XDIST_WORKER"):
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
