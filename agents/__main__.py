from swarmloc.process import pin_blas

pin_blas()  # before numpy loads

from agents.cli import app

app(prog_name="swarmloc")
