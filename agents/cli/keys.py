"""`swarmloc keys`: the swarm's key directory (frame key, certificate authority, members'
certificates, revocations; docs/security.md)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from agents.cli.common import SwarmOpt
from agents.control import Failure
from swarmloc.wire.auth import DIRECTORY_FILE, KEY_FILE, SECRET_SUFFIX

app = typer.Typer(no_args_is_help=True, help="The swarm's keys: the frame key and the certificates of its "
                  "members (docs/security.md).")

KeyDir = typer.Argument(..., metavar="DIRECTORY", help="the swarm's key directory")


def load_keyring(directory: Path):
    from swarmloc.wire.auth import Keyring

    try:
        return Keyring.load(directory / KEY_FILE)
    except ValueError as exc:
        raise Failure(str(exc), 2) from None


def _fingerprint(data: bytes) -> str:
    import hashlib

    return hashlib.sha256(data).hexdigest()[:16]


def _member(name: str) -> str:
    """A member's certificate name: `3` and `agent-3` are agent 3's."""
    return f"agent-{name}" if name.isdigit() else name


@app.command("new")
def keys_new(directory: Path = KeyDir, swarm: str = SwarmOpt):
    """Create a swarm's key directory (mode 0700): the hub's master secret (swarm.key), the
    directory of members' public keys (members.json), netsim's and the operator's own keys
    (netsim.secret, operator.secret) and the swarm's certificate authority (ca.pem, ca.key) that
    `keys add` signs members' certificates with."""
    from agents import tls
    from swarmloc.wire.auth import Keyring

    if (directory / KEY_FILE).exists() or (directory / tls.CA_KEY).exists():
        raise Failure(f"{directory} already holds a swarm's keys; `keys rotate` replaces the frame key", 2)
    try:
        directory.mkdir(mode=0o700, parents=True, exist_ok=True)
        ring = Keyring.generate(swarm)
        ring.save_directory(directory)
        tls.new_ca(directory, swarm)
    except OSError as exc:
        raise Failure(f"cannot write {directory}: {exc.strerror or exc}") from None
    typer.echo(f"{directory}: swarm {swarm}; hub key in {KEY_FILE} (keep it here and on netsim); members netsim, "
               f"operator in {DIRECTORY_FILE}; certificate authority ca.pem, ca.key (keep ca.key here, give members ca.pem)")


@app.command("add")
def keys_add(directory: Path = KeyDir,
             name: str = typer.Argument(..., metavar="NAME", help="an agent id (3 or agent-3), netsim, operator or router"),
             host: Optional[list[str]] = typer.Option(None, "--host", help="an address or DNS name the member "
                                                      "listens on, put in its certificate (repeatable)")):
    """A member's own frame keys (NAME.secret; a revoked member comes back under new ones) and its
    certificate (NAME.pem, NAME.key, signed by the swarm's CA) for Zenoh TLS."""
    from agents import tls

    ring = load_keyring(directory)
    member = _member(name)
    if member != "router":  # the router seals no frames
        ring.add(member)
        ring.save_directory(directory, [member])
    try:
        cert, key = tls.issue(directory, member, host or [])
    except (ValueError, FileNotFoundError) as exc:
        raise Failure(f"{directory}: {exc}", 2) from None
    revoked = revoked_members(directory)
    if member in revoked:
        revoked.remove(member)
        (directory / "revoked.json").write_text(json.dumps(sorted(revoked)))
    secret = "" if member == "router" else f", {directory / (member + SECRET_SUFFIX)}"
    typer.echo(f"{cert}, {key}{secret}: give the member these, ca.pem and {DIRECTORY_FILE}")


def revoked_members(directory: Path) -> set[str]:
    path = directory / "revoked.json"
    return set(json.loads(path.read_text())) if path.exists() else set()


@app.command("revoke")
def keys_revoke(directory: Path = KeyDir, name: str = typer.Argument(..., metavar="NAME", help="an agent id, netsim, operator or router")):
    """Revoke a member: its certificate is deleted and listed as revoked (access control grants it
    nothing), and its frame keys are listed as revoked in members.json: every frame it seals is
    refused by whoever holds the new members.json. Nobody else's keys change."""
    member = _member(name)
    ring = load_keyring(directory)
    for suffix in (".pem", ".key"):
        (directory / f"{member}{suffix}").unlink(missing_ok=True)
    revoked = revoked_members(directory) | {member}
    (directory / "revoked.json").write_text(json.dumps(sorted(revoked)))
    ring.revoke(member)
    ring.save_directory(directory, [])
    typer.echo(f"{member} revoked: its keys open nothing more where the new {DIRECTORY_FILE} is (netsim reads it from "
               f"{KEY_FILE}); copy {DIRECTORY_FILE} to the other members; their own keys are unchanged")


@app.command("rotate")
def keys_rotate(directory: Path = KeyDir):
    """Replace the hub's master secret (a copy of swarm.key was lost): every member's keys change,
    so every member needs its new NAME.secret and members.json."""
    ring = load_keyring(directory)
    ring.rotate()
    ring.save_directory(directory)
    typer.echo(f"{directory / KEY_FILE}: new hub key; every member's keys replaced: copy each its NAME{SECRET_SUFFIX} "
               f"and {DIRECTORY_FILE} and restart it")


@app.command("show")
def keys_show(directory: Path = KeyDir):
    """A key directory's swarm, key fingerprints, members and revocations (never a key)."""
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding

    ring = load_keyring(directory)
    typer.echo(f"{directory}: swarm {ring.swarm}")
    for name, epoch in sorted(ring.members.items()):
        typer.echo(f"  {name:<16} keys generation {epoch}  public sha256 {ring.fingerprint(name)}"
                   + ("  (revoked)" if name in ring.revoked else ""))
    for pem in sorted(directory.glob("*.pem")):
        cert = x509.load_pem_x509_certificate(pem.read_bytes())
        cn = cert.subject.get_attributes_for_oid(x509.NameOID.COMMON_NAME)[0].value
        typer.echo(f"  {pem.name:<16} {cn:<28} until {cert.not_valid_after_utc:%Y-%m-%d}  "
                   f"sha256 {_fingerprint(cert.public_bytes(Encoding.DER))}")
    revoked = revoked_members(directory)
    typer.echo(f"  revoked: {', '.join(sorted(revoked)) or 'none'}")
