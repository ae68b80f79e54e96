from agents.cli import app

app(prog_name="swarmloc")
