"""agents: the per-agent daemon hosting one swarmloc node over Zenoh, and the swarmloc CLI."""
