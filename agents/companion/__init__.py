"""What the agent daemon needs on a companion computer beside a flight controller: the MAVLink
adapter (mavlink.py), sensor sources (sources.py) and the systemd service (service.py). The agent
configuration file that sets them up is agents/config.py."""
