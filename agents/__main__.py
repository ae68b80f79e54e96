import os

# Dozens of agent processes share two cores: a BLAS thread pool per process only spins and
# steals them (measured: 7 ms per 4x4 triangular solve with the default pool).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from agents.cli import app

app(prog_name="swarmloc")
