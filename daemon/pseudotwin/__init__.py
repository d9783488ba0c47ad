"""pseudotwin: Corr-GP pseudo-measurements of desk temperature and CO2 for building MPC."""

import logging as _logging
import os as _os

# The matrices here are small (a day of readings): one BLAS thread is fastest, and a
# multi-threaded BLAS in each of several worker processes oversubscribes a 2-core edge box.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
# GPy logs every model construction at INFO; that is noise for a daemon.
_logging.getLogger("GP").setLevel(_logging.WARNING)
_logging.getLogger("paramz").setLevel(_logging.WARNING)

__version__ = "0.1.0"
