import os
import sys

# Before numpy loads OpenBLAS: a fit's linear algebra is small banded solves and thin
# products, where BLAS threads only wait on each other (the standard set's joint fit took
# 2.4-3x longer with 2 threads than with 1 on a busy 2-core machine).  A value the user
# set wins; Dask's workers get the same from their nanny.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from identify.cli import main  # noqa: E402

sys.exit(main())
