"""The command line, fleet runners, reports and plots.

Importing any of it first pins the BLAS thread pools to one thread, before numpy loads (unless the
environment says otherwise): the estimators work on tiny matrices, where a multi-threaded BLAS only
spins against the Python thread (measured: the demo ran 2.6× slower on 2 cores). Processes that
``deploy`` starts (agents, study workers) import it first too, so this is the one place it is set.
"""

import os

THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")

for _variable in THREAD_VARIABLES:
    os.environ.setdefault(_variable, "1")
