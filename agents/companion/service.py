"""`swarmloc install-service`: the agent of a configuration file as a systemd service.

systemd does what a companion computer needs and the daemon does not: start at boot, restart
after a crash (the agent resumes from its checkpoint in `state_dir`), collect stderr in the
journal. This module only writes the unit and prepares the state directory; it never runs
systemctl, so it works (and is tested) on machines without systemd.
"""

from __future__ import annotations

import os
import pwd
import re
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

SYSTEM_UNIT_DIR = Path("/etc/systemd/system")
UNIT_NAME = re.compile(r"[A-Za-z0-9:_.\\-]+")  # systemd's unit name characters, '@' (templates) excluded
PLAIN_ARG = re.compile(r"[A-Za-z0-9_@%+=:,./-]+")

# The agent exits 143 on SIGTERM (swarmloc.exit_on_sigterm), and 2 on a configuration that
# cannot start, which no restart mends.
SIGTERM_EXIT, BAD_CONFIG_EXIT = 143, 2


@dataclass(frozen=True)
class Plan:
    """What an installation writes: the unit and where it goes, the state directory and its owner."""

    name: str  # the unit's name, with .service
    path: Path
    text: str
    state_dir: Path | None
    user: str | None
    user_unit: bool  # under a systemd/user directory: managed with `systemctl --user`


def _escape(value: str) -> str:
    """A value as systemd reads it literally: its specifiers (%) doubled."""
    return value.replace("%", "%%")


def _quote(arg: str) -> str:
    """One word of ExecStart: systemd splits on blanks and honours double quotes with backslash
    escapes, which is also what shlex.split reads; it also expands $VARIABLES there."""
    arg = _escape(arg).replace("$", "$$")
    if PLAIN_ARG.fullmatch(arg):
        return arg
    return '"' + arg.replace("\\", "\\\\").replace('"', '\\"') + '"'


def unit_name(agent_id: int, name: str | None) -> str:
    """`swarmloc-agent-<id>.service`, or --name (with `.service` added if it lacks it)."""
    name = name or f"swarmloc-agent-{agent_id}"
    if not UNIT_NAME.fullmatch(name):
        raise ValueError(f"{name!r} is not a systemd unit name (letters, digits and : _ . \\ - only)")
    return name if name.endswith(".service") else f"{name}.service"


def is_user_unit_dir(unit_dir: Path) -> bool:
    return unit_dir.parts[-2:] == ("systemd", "user")


def plan(config: Path, cfg, name: str | None = None, unit_dir: Path = SYSTEM_UNIT_DIR,
         user: str | None = None, python: str = sys.executable) -> Plan:
    """The unit for the validated configuration `cfg` read from `config` (ValueError: a bad
    --name, --user or combination). Paths are made absolute without resolving symlinks, so a
    config reached through a link stays reached through it."""
    config = Path(os.path.abspath(config))
    unit_dir = Path(os.path.abspath(unit_dir))
    user_unit = is_user_unit_dir(unit_dir)
    if user is not None:
        if user_unit:
            raise ValueError("--user is for a system unit: a user unit runs as the user whose manager starts it")
        try:
            pwd.getpwnam(user)
        except KeyError:
            raise ValueError(f"no such user {user!r}") from None
    for path in (config, Path(python)):
        if "\n" in str(path):
            raise ValueError(f"{str(path)!r}: a path with a newline cannot go into a unit file")
    name = unit_name(cfg.id, name)
    # -P: the working directory is the config's, and a package there named like ours must not
    # shadow the installed one.
    exec_start = " ".join(_quote(a) for a in (os.path.abspath(python), "-P", "-m", "agents", "agent", "--config",
                                              str(config)))
    lines = [
        f"# Written by `swarmloc install-service --config {config}`; the configuration file is the",
        "# agent: edit it and restart; reinstall when it or the Python environment moves.",
        "[Unit]",
        f"Description=swarmloc agent {cfg.id} of swarm {cfg.swarm} ({cfg.estimator.name})",
        # Its Zenoh endpoints may name addresses that exist only once the network is up.
        "Wants=network-online.target",
        "After=network-online.target",
        "",
        "[Service]",
        "Type=exec",
        f"ExecStart={exec_start}",
        f"WorkingDirectory={_escape(str(config.parent))}",
        *([f"User={user}"] if user else []),
        "Restart=on-failure",
        "RestartSec=2",
        f"RestartPreventExitStatus={BAD_CONFIG_EXIT}",
        f"SuccessExitStatus={SIGTERM_EXIT}",
        "KillSignal=SIGTERM",
        "TimeoutStopSec=5",
        "StandardOutput=journal",
        "StandardError=journal",
        "",
        "[Install]",
        f"WantedBy={'default.target' if user_unit else 'multi-user.target'}",
    ]
    return Plan(name, unit_dir / name, "\n".join(lines) + "\n", cfg.state_dir, user, user_unit)


def prepare_state_dir(p: Plan) -> str | None:
    """Create the state directory, mode 0700, owned by the service's user; a note on what was
    found when it already exists, which is left as it is (it may be shared, like /var/lib)."""
    d = p.state_dir
    if d is None:
        return None
    if d.exists():
        if not d.is_dir():
            raise OSError(f"state_dir {d} exists and is not a directory")
        st = d.stat()
        owner = _user_of(st.st_uid)
        if (p.user is not None and owner != p.user) or st.st_mode & 0o077:
            return (f"state_dir {d} exists and is left as it is (owner {owner}, mode {st.st_mode & 0o777:04o}); "
                    f"the agent{f' (user {p.user})' if p.user else ''} must be able to write it")
        return None
    d.mkdir(mode=0o700, parents=True)
    d.chmod(0o700)  # mkdir's mode is cut by the umask
    if p.user is not None:
        entry = pwd.getpwnam(p.user)
        os.chown(d, entry.pw_uid, entry.pw_gid)
    return None


def _user_of(uid: int) -> str:
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return str(uid)


def write_unit(p: Plan) -> bool:
    """Write the unit, mode 0644, atomically; True if it replaced one."""
    p.path.parent.mkdir(parents=True, exist_ok=True)
    existed = p.path.exists()
    tmp = p.path.with_name(f".{p.name}.{os.getpid()}")
    with os.fdopen(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644), "w") as f:
        f.write(p.text)
    tmp.chmod(0o644)  # the umask again: systemd reads units as whoever it runs as
    os.replace(tmp, p.path)
    return existed


def next_commands(p: Plan) -> list[str]:
    """What to run once the unit is in place."""
    scope = " --user" if p.user_unit else ""
    return [f"systemctl{scope} daemon-reload && systemctl{scope} enable --now {p.name}",
            f"journalctl{scope} -u {p.name} -f"]


def systemd_absent() -> str | None:
    """Why systemctl cannot manage services here, or None when it can. /run/systemd/system is
    the test sd_booted(3) makes: containers and CI often ship systemctl without running systemd."""
    if shutil.which("systemctl") is None:
        return "systemctl is not installed here"
    if not Path("/run/systemd/system").is_dir():
        return "systemd is not running here: no /run/systemd/system"
    return None
