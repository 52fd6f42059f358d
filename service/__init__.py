"""bdsfix: BeiDou receiver service with the Zhao-Cui-Lu a-priori-free fast first fix."""

import os

__version__ = "0.1.0"

# One BLAS thread unless the user says otherwise: bdsfix's matrices are a few unknowns wide
# (never worth a second thread), and OpenBLAS starts a thread per core when numpy loads,
# which cost ~30 ms of CPU at each start of `bdsfix solve` (HKSC, 2-core machine), and its
# idle threads spin beside the daemon's. Set here, before any module of bdsfix imports numpy.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
