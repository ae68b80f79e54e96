"""The `swarmloc` command line, one module per command group:

  catalog.py   estimators, scenarios         what can run, and the built-in scenarios
  run.py       run, demo, replay             a swarm of agent processes with netsim
  calibrate.py calibrate                     a recording's noise model, for replay --noise
  study.py     study                         Monte Carlo sweeps
  deploy.py    agent, router, install-service  a companion computer's agent, router and service
  faults.py    inject ..., clear, faults     faults in a running swarm
  status.py    status, stop                  watch a running swarm, end it
  keys.py      keys ...                      the swarm's key directory
  common.py    errors, option checks and the options every command shares

Only the commands live here: agents/launcher.py runs a swarm (netsim is started as a separate
process, `python -m netsim`, so agents and netsim still never import each other) and
agents/control.py talks to a running one. The launcher, rich and Zenoh are imported inside the
commands that need them, so `swarmloc agent` starts without them.
"""

import typer

from agents.cli import calibrate, catalog, deploy, faults, keys, run, status, study
from agents.cli.common import SwarmlocGroup

app = typer.Typer(cls=SwarmlocGroup, add_completion=False, no_args_is_help=True,
                  help="swarmloc: cooperative localization over a real (or emulated) network.")
for _commands in (catalog, run, calibrate, study, deploy):
    app.add_typer(_commands.app)
app.add_typer(faults.inject_app, name="inject")
app.add_typer(keys.app, name="keys")
for _commands in (faults, status):
    app.add_typer(_commands.app)
