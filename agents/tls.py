"""Transport security for a swarm: a swarm CA, member certificates, and the Zenoh configuration
that uses them (TLS, mutual TLS) plus an access-control list keyed by certificate names.

Library functions only (`swarmloc keys` wires a command to them):

    new_ca(directory, swarm)            -> ca.pem, ca.key          (directory 0700, keys 0600)
    issue(directory, name, hosts)       -> <name>.pem, <name>.key  signed by ca.key
    zenoh_tls(config, directory, name)  -> config dict with transport.link.tls and tls/ endpoints
    zenoh_acl(config, swarm, agent_ids) -> config dict with an access_control block

A member's name is its certificate's Common Name and its identity in the ACL: "agent-<id>",
"netsim", "operator" or "router". Keys are ECDSA P-256 by default (Ed25519 also works with
Zenoh's rustls/ring; tests/test_tls.py checks both), unencrypted PKCS#8 PEM, because Zenoh
reads its key files without a passphrase: the file mode (0600) and the directory's (0700) are
their only protection. Only `new_ca` and `issue` read or write ca.key; a member needs ca.pem,
<name>.pem and <name>.key, nothing else, and `zenoh_tls` refers to nothing else.

The key-expression grammar is swarmloc.wire.Keys (docs/wire.md section 2); docs/security.md
describes the rule set `zenoh_acl` produces.
"""

from __future__ import annotations

import datetime as _dt
import ipaddress
import json
import os
import re
import tempfile
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from swarmloc.wire import Keys

CA_CERT, CA_KEY = "ca.pem", "ca.key"
ALGORITHMS = ("p256", "ed25519")
NAME_RE = re.compile(r"^(agent-(0|[1-9][0-9]{0,9})|netsim|operator|router)$")
CA_DAYS = 3650
MEMBER_DAYS = 365

# Endpoints zenoh_tls accepts: tcp/ is rewritten to tls/; quic/ uses the same transport.link.tls
# settings. Any other protocol would carry the swarm unauthenticated, so zenoh_tls refuses it.
_SECURE = ("tls/", "quic/")


# --------------------------------------------------------------------------- files


def _write_private(path: Path, data: bytes) -> None:
    """Write `data` to `path` with mode 0600 from the first byte (a temporary file in the same
    directory, created 0600 by mkstemp, then renamed over `path`)."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        os.fchmod(fd, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def _write_public(path: Path, data: bytes) -> None:
    _write_private(path, data)
    os.chmod(path, 0o644)


def _new_key(algorithm: str):
    if algorithm == "p256":
        return ec.generate_private_key(ec.SECP256R1())
    if algorithm == "ed25519":
        return ed25519.Ed25519PrivateKey.generate()
    raise ValueError(f"unknown key algorithm {algorithm!r} (one of {', '.join(ALGORITHMS)})")


def _key_pem(key) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _sign_hash(key):
    """The digest to sign with: SHA-256 for ECDSA, none for Ed25519 (it hashes internally)."""
    return None if isinstance(key, ed25519.Ed25519PrivateKey) else hashes.SHA256()


def _now() -> _dt.datetime:
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0)


# --------------------------------------------------------------------------- CA and members


def new_ca(directory: str | os.PathLike, swarm: str, algorithm: str = "p256", days: int = CA_DAYS) -> Path:
    """Create the swarm CA: `directory`/ca.pem (the certificate every member trusts) and
    `directory`/ca.key (mode 0600; signs members' certificates, nothing else). The directory is
    created, or its mode set, to 0700. Refuses (FileExistsError) to replace an existing ca.key:
    a new CA invalidates every certificate the old one issued. Returns ca.pem's path."""
    Keys(swarm)  # same rules as the key expressions: non-empty, no / * $ # ?
    d = Path(directory)
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    os.chmod(d, 0o700)
    if (d / CA_KEY).exists():
        raise FileExistsError(f"{d / CA_KEY} exists; remove it to start a new CA")
    key = _new_key(algorithm)
    # A CA's name is unique (a random tag), so a certificate from another CA of the same swarm
    # name is refused as UnknownIssuer, not matched by name and refused as BadSignature.
    subject = x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "swarmloc"),
                         x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, swarm),
                         x509.NameAttribute(NameOID.COMMON_NAME, f"swarmloc {swarm} CA {os.urandom(4).hex()}")])
    now = _now()
    ski = x509.SubjectKeyIdentifier.from_public_key(key.public_key())
    cert = (x509.CertificateBuilder()
            .subject_name(subject).issuer_name(subject)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - _dt.timedelta(minutes=5))
            .not_valid_after(now + _dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False,
                                         key_encipherment=False, data_encipherment=False,
                                         key_agreement=False, key_cert_sign=True, crl_sign=True,
                                         encipher_only=False, decipher_only=False), critical=True)
            .add_extension(ski, critical=False)
            .sign(key, _sign_hash(key)))
    _write_private(d / CA_KEY, _key_pem(key))
    _write_public(d / CA_CERT, cert.public_bytes(serialization.Encoding.PEM))
    return d / CA_CERT


def _host(h: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(h))
    except ValueError:
        return x509.DNSName(h)


def issue(directory: str | os.PathLike, name: str, hosts: list[str] | tuple[str, ...] = (),
          algorithm: str | None = None, days: int = MEMBER_DAYS) -> tuple[Path, Path]:
    """Issue `name`'s certificate, signed by `directory`'s CA: `directory`/<name>.pem (mode
    0644) and <name>.key (0600), replacing earlier ones (renewal). `name` is "agent-<id>",
    "netsim", "operator" or "router" and becomes the certificate's Common Name, the identity
    the ACL matches. `hosts` (DNS names and IP addresses) go into subjectAltName: a member that
    listens needs the names/addresses others dial it at (Zenoh verifies them); a client-only
    member may have none. The key algorithm is the CA's unless given. Extended key usage is
    both serverAuth and clientAuth (a peer both listens and connects). Returns the two paths."""
    if not NAME_RE.match(name):
        raise ValueError(f"bad member name {name!r}: agent-<id>, netsim, operator or router")
    d = Path(directory)
    ca_key = serialization.load_pem_private_key((d / CA_KEY).read_bytes(), password=None)
    ca_cert = x509.load_pem_x509_certificate((d / CA_CERT).read_bytes())
    if algorithm is None:
        algorithm = "ed25519" if isinstance(ca_key, ed25519.Ed25519PrivateKey) else "p256"
    key = _new_key(algorithm)
    swarm = ca_cert.subject.get_attributes_for_oid(NameOID.ORGANIZATIONAL_UNIT_NAME)[0].value
    subject = x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "swarmloc"),
                         x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, swarm),
                         x509.NameAttribute(NameOID.COMMON_NAME, name)])
    now = _now()
    b = (x509.CertificateBuilder()
         .subject_name(subject).issuer_name(ca_cert.subject)
         .public_key(key.public_key())
         .serial_number(x509.random_serial_number())
         .not_valid_before(now - _dt.timedelta(minutes=5))
         .not_valid_after(min(now + _dt.timedelta(days=days), ca_cert.not_valid_after_utc))
         .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
         .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False,
                                      key_encipherment=False, data_encipherment=False,
                                      key_agreement=False, key_cert_sign=False, crl_sign=False,
                                      encipher_only=False, decipher_only=False), critical=True)
         .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                               ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
         .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
         .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                        critical=False))
    if hosts:
        b = b.add_extension(x509.SubjectAlternativeName([_host(h) for h in hosts]), critical=False)
    cert = b.sign(ca_key, _sign_hash(ca_key))
    _write_private(d / f"{name}.key", _key_pem(key))
    _write_public(d / f"{name}.pem", cert.public_bytes(serialization.Encoding.PEM))
    return d / f"{name}.pem", d / f"{name}.key"


# --------------------------------------------------------------------------- Zenoh configuration


def _as_dict(config: dict | str) -> dict:
    """A copy of a zenoh config: the JSON string swarmloc.wire.zenoh_config returns, or its dict."""
    return json.loads(config) if isinstance(config, str) else json.loads(json.dumps(config))


def _secure_endpoints(eps: list[str]) -> list[str]:
    out = []
    for ep in eps:
        if ep.startswith("tcp/"):
            ep = "tls/" + ep[len("tcp/"):]
        if not ep.startswith(_SECURE):
            raise ValueError(f"endpoint {ep!r} would bypass TLS (only tcp/ -> tls/ and quic/ are allowed)")
        out.append(ep)
    return out


def zenoh_tls(config: dict | str, directory: str | os.PathLike, name: str, mutual: bool = True) -> dict:
    """`config` (wire.zenoh_config's JSON or its dict; not modified) with TLS: every tcp/
    endpoint becomes tls/ (other non-TLS protocols are refused with ValueError), and
    transport.link.tls names `directory`'s ca.pem as the only CA the member adds to Zenoh's
    trust store, and <name>.pem/<name>.key as its certificate both when listening and when
    connecting. `mutual`: enable_mtls, so a listener refuses a client without a certificate
    signed by the CA, and a connector presents its own (the ACL's subject). Server names are
    verified (verify_name_on_connect), and links close when the peer's certificate expires.
    Paths are absolute. The files must exist (FileNotFoundError otherwise)."""
    if not NAME_RE.match(name):
        raise ValueError(f"bad member name {name!r}")
    d = Path(directory).resolve()
    files = {"ca": d / CA_CERT, "cert": d / f"{name}.pem", "key": d / f"{name}.key"}
    for p in files.values():
        if not p.is_file():
            raise FileNotFoundError(p)
    cfg = _as_dict(config)
    for side in ("listen", "connect"):
        if side in cfg:
            cfg[side]["endpoints"] = _secure_endpoints(cfg[side].get("endpoints", []))
    link = cfg.setdefault("transport", {}).setdefault("link", {})
    link["tls"] = {
        "root_ca_certificate": str(files["ca"]),
        "listen_private_key": str(files["key"]),
        "listen_certificate": str(files["cert"]),
        "enable_mtls": bool(mutual),
        "connect_private_key": str(files["key"]),
        "connect_certificate": str(files["cert"]),
        "verify_name_on_connect": True,
        "close_link_on_expiration": True,
    }
    return cfg


def _rule(rid: str, messages: list[str], flow: str, keys: list[str]) -> dict:
    return {"id": rid, "messages": messages, "flows": [flow], "permission": "allow", "key_exprs": keys}


def acl_rules(swarm: str, agent_ids, direct: bool = False) -> dict:
    """The access_control block zenoh_acl adds (see there)."""
    k = Keys(swarm)
    p = k.prefix
    ids = sorted({int(a) for a in agent_ids})
    rules, subjects, policies = [], [], []

    def member(sid: str, cn: str, rule_ids: list[str]):
        subjects.append({"id": sid, "cert_common_names": [cn]})
        policies.append({"id": f"{sid}-policy", "rules": rule_ids, "subjects": [sid]})

    # An agent. "in": what its session may send the router; "out": what the router may
    # forward to it. Its own keys only, except radio/rx/* in direct mode.
    for a in ids:
        r = f"agent-{a}"
        puts = [k.radio_tx(a), k.estimate(a), k.done(a), k.command(a)] + ([f"{p}/radio/rx/*"] if direct else [])
        rules += [
            _rule(f"{r}-put", ["put"], "ingress", puts),
            # Others' subscriptions forwarded to it: without them a Zenoh publisher's write
            # filter drops its puts before they leave the session. A rule must include the
            # subscription's key expression (an operator's agent/*/estimate), hence the whole
            # swarm's; a declaration lets it put nothing its put rule does not.
            _rule(f"{r}-put-interest", ["declare_subscriber"], "egress", [f"{p}/**"]),
            _rule(f"{r}-sub", ["declare_subscriber"], "ingress",
                  [k.clock, k.sensors(a), k.radio_rx(a), k.radio_rx("all")]),
            _rule(f"{r}-recv", ["put"], "egress", [k.clock, k.sensors(a), k.radio_rx(a), k.radio_rx("all")]),
            _rule(f"{r}-stats", ["declare_queryable"], "ingress", [k.stats(a)]),
            # netsim asks agent/*/stats at the end of a run. A rule must include the key
            # expression checked, and Zenoh checks a query AND its replies against the query's
            # key expression (not the reply's key), so agent/<id>/stats alone would refuse both.
            _rule(f"{r}-stats-query", ["query"], "egress", [k.stats(a), f"{p}/agent/*/stats"]),
            _rule(f"{r}-stats-reply", ["reply"], "ingress", [k.stats(a), f"{p}/agent/*/stats"]),
            _rule(f"{r}-alive", ["liveliness_token"], "ingress", [k.alive(a)]),
        ]
        if direct:  # membership of the others (docs/wire.md, "Direct mode")
            rules += [
                _rule(f"{r}-peers", ["declare_liveliness_subscriber", "liveliness_query"], "ingress",
                      [f"{p}/agent/*/alive"]),
                _rule(f"{r}-peers-alive", ["liveliness_token"], "egress", [f"{p}/agent/*/alive"]),
            ]
        member(r, r, [x["id"] for x in rules if x["id"].startswith(r + "-")])

    # netsim, when it is a client of a separate router (as the router itself its own session is
    # not subject to the ACL; the rules for the others still apply to what it sends them).
    n = [
        _rule("netsim-put", ["put"], "ingress",
              [k.clock, f"{p}/agent/*/sensors", f"{p}/truth/*", f"{p}/radio/rx/*", k.links, k.events]),
        _rule("netsim-sub", ["declare_subscriber"], "ingress",
              [f"{p}/radio/tx/*", f"{p}/agent/*/estimate", f"{p}/agent/*/done", f"{p}/agent/*/command"]),
        _rule("netsim-recv", ["put"], "egress",
              [f"{p}/radio/tx/*", f"{p}/agent/*/estimate", f"{p}/agent/*/done", f"{p}/agent/*/command"]),
        _rule("netsim-alive", ["declare_liveliness_subscriber", "liveliness_query"], "ingress", [f"{p}/agent/*/alive"]),
        _rule("netsim-alive-recv", ["liveliness_token"], "egress", [f"{p}/agent/*/alive"]),
        _rule("netsim-control", ["declare_queryable", "reply"], "ingress", [k.control]),
        _rule("netsim-control-query", ["query"], "egress", [k.control]),
        _rule("netsim-stats", ["query"], "ingress", [f"{p}/agent/*/stats"]),
        _rule("netsim-stats-reply", ["reply"], "egress", [f"{p}/agent/*/stats"]),
    ]
    rules += n
    member("netsim", "netsim", [x["id"] for x in n])

    # The operator (CLI, monitors): reads everything, asks netsim/control and agent stats.
    o = [
        _rule("operator-sub", ["declare_subscriber"], "ingress", [f"{p}/**"]),
        _rule("operator-recv", ["put"], "egress", [f"{p}/**"]),
        _rule("operator-query", ["query"], "ingress", [k.control, f"{p}/agent/*/stats"]),
        _rule("operator-reply", ["reply"], "egress", [k.control, f"{p}/agent/*/stats"]),
        _rule("operator-alive", ["declare_liveliness_subscriber", "liveliness_query"], "ingress", [f"{p}/agent/*/alive"]),
        _rule("operator-alive-recv", ["liveliness_token"], "egress", [f"{p}/agent/*/alive"]),
    ]
    rules += o
    member("operator", "operator", [x["id"] for x in o])
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def zenoh_acl(config: dict | str, swarm: str, agent_ids, direct: bool = False) -> dict:
    """`config` (not modified) with Zenoh access control, for the router (or, in direct mode,
    every peer): default deny, and per certificate Common Name (so it needs zenoh_tls with
    mutual=True: a session without a client certificate matches no subject and may do nothing):

    - agent-<id>: put on radio/tx/<id>, agent/<id>/estimate and agent/<id>/done (with `direct`,
      also radio/rx/*); subscribe to and receive clock, agent/<id>/sensors, radio/rx/<id> and
      radio/rx/all; declare and answer the queryable agent/<id>/stats; hold the liveliness
      token agent/<id>/alive (with `direct`, also watch agent/*/alive).
    - netsim: put on clock, agent/*/sensors, truth/*, radio/rx/*, netsim/links, netsim/events;
      receive radio/tx/*, agent/*/estimate, agent/*/done; watch agent/*/alive; declare and
      answer netsim/control; query agent/*/stats.
    - operator: subscribe to and receive swarmloc/<swarm>/**; query and get replies from
      netsim/control and agent/*/stats; watch agent/*/alive. Publishes nothing.

    Everything else, including any key outside swarmloc/<swarm>/, is denied. Rules are
    per flow: "ingress" is what the member's session sends the router, "egress" what the router
    forwards to it."""
    cfg = _as_dict(config)
    cfg["access_control"] = acl_rules(swarm, agent_ids, direct)
    return cfg
