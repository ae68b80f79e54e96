"""agents/tls.py: the swarm CA, member certificates, and real Zenoh sessions (in this process, on
127.0.0.1 only) over TLS, mutual TLS and the access-control list keyed by certificate names.

What a refused client sees (asserted below): zenoh.open raises zenoh.ZError "Unable to connect
to any of [Single(tls/127.0.0.1:<port>)]!" at once; the reason (CertificateRequired,
UnknownIssuer, ...) is only in Zenoh's log. What the ACL refuses is dropped without a word: the
publisher's put returns normally and the subscriber never gets the sample; a query gets no
reply from a queryable the ACL hides."""

import json
import os
import stat
import time

import pytest
import zenoh
from conftest import free_port
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from agents import tls
from swarmloc import wire

SWARM = "s"
P = f"swarmloc/{SWARM}"
MEMBERS = ("router", "netsim", "operator", "agent-1", "agent-2")


def _pki(tmp_path, algorithm="p256", name="keys"):
    d = tmp_path / name
    tls.new_ca(d, SWARM, algorithm=algorithm)
    for m in MEMBERS:
        tls.issue(d, m, ["127.0.0.1"])
    return d


def _open(cfg: dict) -> zenoh.Session:
    return zenoh.open(zenoh.Config.from_json5(json.dumps(cfg)))


class Net:
    """A TLS router on 127.0.0.1 (mutual TLS, optionally the ACL) and clients by member name."""

    def __init__(self, d, acl=False, direct=False, router_name="router", mutual=True):
        self.d = d
        self.port = free_port()
        self.ep = f"tcp/127.0.0.1:{self.port}"
        cfg = tls.zenoh_tls(wire.zenoh_config("router", [self.ep]), d, router_name, mutual=mutual)
        if acl:
            cfg = tls.zenoh_acl(cfg, SWARM, [1, 2], direct=direct)
        self.router = _open(cfg)
        self.sessions = [self.router]

    def client_config(self, name, d=None, mutual=True):
        return tls.zenoh_tls(wire.zenoh_config("client", connect=[self.ep]), d or self.d, name, mutual=mutual)

    def client(self, name, **kw):
        s = _open(self.client_config(name, **kw))
        self.sessions.append(s)
        return s

    def close(self):
        for s in reversed(self.sessions):
            s.close()


@pytest.fixture
def pki(tmp_path):
    return _pki(tmp_path)


@pytest.fixture
def acl_net(pki):
    n = Net(pki, acl=True)
    yield n
    n.close()


class Inbox:
    """Samples a subscriber got, as (key, payload) pairs."""

    def __init__(self):
        self.items = []

    def __call__(self, sample):
        self.items.append((str(sample.key_expr), sample.payload.to_bytes()))

    def wait(self, item, timeout=3.0):
        deadline = time.monotonic() + timeout
        while item not in self.items:
            assert time.monotonic() < deadline, f"{item} not received; got {self.items}"
            time.sleep(0.01)


def _ready(pub, key, inbox):
    """Publish a marker on `key` until `inbox` gets it: the subscriber's declaration has reached
    the router (declarations propagate asynchronously)."""
    deadline = time.monotonic() + 5
    while (key, b"ready") not in inbox.items:
        assert time.monotonic() < deadline, f"subscriber never ready; got {inbox.items}"
        pub.put(key, b"ready")
        time.sleep(0.05)


# --------------------------------------------------------------------------- files (c)


def test_key_files_modes_and_certificates(tmp_path):
    d = tmp_path / "keys"
    ca_pem = tls.new_ca(d, SWARM)
    cert_path, key_path = tls.issue(d, "agent-7", ["127.0.0.1", "uav7.local"])
    assert stat.S_IMODE(os.stat(d).st_mode) == 0o700
    assert stat.S_IMODE(os.stat(d / "ca.key").st_mode) == 0o600
    assert stat.S_IMODE(os.stat(key_path).st_mode) == 0o600
    assert stat.S_IMODE(os.stat(ca_pem).st_mode) == 0o644
    assert stat.S_IMODE(os.stat(cert_path).st_mode) == 0o644
    assert sorted(p.name for p in d.iterdir()) == ["agent-7.key", "agent-7.pem", "ca.key", "ca.pem"]  # no temp files left

    ca = x509.load_pem_x509_certificate(ca_pem.read_bytes())
    cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    cert.verify_directly_issued_by(ca)
    assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "agent-7"
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert [str(ip) for ip in san.get_values_for_type(x509.IPAddress)] == ["127.0.0.1"]
    assert san.get_values_for_type(x509.DNSName) == ["uav7.local"]
    eku = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert set(eku) == {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH}
    assert cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca is False
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca is True

    # a directory that exists with a wider mode is narrowed; an existing CA is never replaced
    with pytest.raises(FileExistsError):
        tls.new_ca(d, SWARM)
    wide = tmp_path / "wide"
    wide.mkdir(mode=0o755)
    tls.new_ca(wide, SWARM)
    assert stat.S_IMODE(os.stat(wide).st_mode) == 0o700

    for bad in ("agent-x", "agent-01", "root", "agent-1/..", "../operator"):
        with pytest.raises(ValueError):
            tls.issue(d, bad, [])
    with pytest.raises(ValueError):
        tls.new_ca(tmp_path / "bad", "a/b")


def test_ca_key_never_leaves_the_directory(tmp_path):
    d = _pki(tmp_path)
    ca_key = serialization.load_pem_private_key((d / "ca.key").read_bytes(), password=None)
    ca_der = ca_key.private_bytes(serialization.Encoding.DER, serialization.PrivateFormat.PKCS8,
                                  serialization.NoEncryption())
    for p in d.iterdir():  # no other file holds the CA key, in PEM or DER
        if p.name != "ca.key":
            data = p.read_bytes()
            assert (d / "ca.key").read_bytes() not in data and ca_der not in data, p
    # nothing outside the directory was written
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keys"]
    # a member's configuration names ca.pem and its own two files, never ca.key
    for m in MEMBERS:
        tls_cfg = tls.zenoh_tls(wire.zenoh_config("client", connect=["tcp/127.0.0.1:1"]), d, m)["transport"]["link"]["tls"]
        assert "ca.key" not in json.dumps(tls_cfg)
        assert {v for v in tls_cfg.values() if isinstance(v, str)} == {str(d / "ca.pem"), str(d / f"{m}.pem"), str(d / f"{m}.key")}
    # and a member's machine needs only those three files
    member = tmp_path / "agent-1-only"
    member.mkdir(mode=0o700)
    for f in ("ca.pem", "agent-1.pem", "agent-1.key"):
        (member / f).write_bytes((d / f).read_bytes())
    tls.zenoh_tls(wire.zenoh_config("client"), member, "agent-1")
    with pytest.raises(FileNotFoundError):
        tls.zenoh_tls(wire.zenoh_config("client"), member, "agent-2")


def test_zenoh_tls_config(pki):
    src = wire.zenoh_config("peer", ["tcp/127.0.0.1:7448"], ["tcp/127.0.0.1:7449", "quic/127.0.0.1:7450"])
    before = json.loads(src)
    cfg = tls.zenoh_tls(before, pki, "agent-1")
    assert before == json.loads(src)  # input untouched
    assert cfg["listen"]["endpoints"] == ["tls/127.0.0.1:7448"]
    assert cfg["connect"]["endpoints"] == ["tls/127.0.0.1:7449", "quic/127.0.0.1:7450"]
    assert cfg["transport"]["link"]["rx"] == {"max_message_size": wire.ZENOH_MAX_MESSAGE_BYTES}
    t = cfg["transport"]["link"]["tls"]
    assert t["enable_mtls"] is True and t["verify_name_on_connect"] is True
    assert tls.zenoh_tls(src, pki, "agent-1", mutual=False)["transport"]["link"]["tls"]["enable_mtls"] is False
    # Zenoh 1.10 knows every option (it refuses unknown fields) and reads them back unchanged
    zc = zenoh.Config.from_json5(json.dumps(tls.zenoh_acl(cfg, SWARM, [1, 2])))
    assert json.loads(zc.get_json("transport/link/tls"))["connect_certificate"] == str(pki / "agent-1.pem")
    assert json.loads(zc.get_json("access_control/default_permission")) == "deny"
    for bad in ("udp/127.0.0.1:7447", "ws/127.0.0.1:7447", "unixsock-stream//tmp/s"):
        with pytest.raises(ValueError, match="bypass TLS"):
            tls.zenoh_tls(wire.zenoh_config("client", connect=[bad]), pki, "agent-1")


# --------------------------------------------------------------------------- TLS and mTLS (a)


@pytest.mark.parametrize("algorithm", ["p256", "ed25519"])
def test_mtls_member_connects_and_pubsub_works(tmp_path, algorithm):
    net = Net(_pki(tmp_path, algorithm))
    try:
        agent, op = net.client("agent-1"), net.client("operator")
        inbox = Inbox()
        op.declare_subscriber(f"{P}/**", inbox)
        _ready(agent, f"{P}/radio/tx/1", inbox)
        agent.put(f"{P}/radio/tx/1", b"frame")
        inbox.wait((f"{P}/radio/tx/1", b"frame"))
        # the links really are TLS, and each side knows the other's certificate Common Name
        links = list(net.router.info.links())
        assert sorted(link.auth_identifier for link in links) == ["agent-1", "operator"]
        assert all(str(link.src).startswith("tls/127.0.0.1:") for link in links)
        assert [link.auth_identifier for link in agent.info.links()] == ["router"]
    finally:
        net.close()


def test_clients_without_a_swarm_certificate_cannot_connect(tmp_path):
    d = _pki(tmp_path)
    other = _pki(tmp_path, name="other")  # another CA, same swarm name and member names
    net = Net(d)
    try:
        refused = {
            # trusts the swarm CA but presents no certificate (the server wants one: CertificateRequired)
            "no certificate": net.client_config("agent-1", mutual=False),
            # trusts the swarm CA, presents agent-1 from another CA (the server: UnknownIssuer)
            "other CA": {**net.client_config("agent-1", d=other)},
            # plain TCP to a TLS listener
            "plain tcp": json.loads(wire.zenoh_config("client", connect=[net.ep])),
        }
        refused["other CA"]["transport"]["link"]["tls"]["root_ca_certificate"] = str(d / "ca.pem")
        # a client that does not trust the router's CA refuses it (client side: UnknownIssuer)
        refused["distrusts router"] = net.client_config("agent-1", d=other)
        for what, cfg in refused.items():
            t = time.monotonic()
            with pytest.raises(zenoh.ZError, match=r"Unable to connect to any of \[Single\((tls|tcp)/127\.0\.0\.1:%d\)\]" % net.port):
                _open(cfg)
            assert time.monotonic() - t < 3, what  # refused at once, not after a timeout
        # the router is still serving its members
        net.client("operator")
    finally:
        net.close()


def test_server_name_is_verified(tmp_path):
    d = tmp_path / "keys"
    tls.new_ca(d, SWARM)
    tls.issue(d, "router", ["10.99.99.99"])  # not the address the client dials
    tls.issue(d, "agent-1")
    port = free_port()
    router = _open(tls.zenoh_tls(wire.zenoh_config("router", [f"tcp/127.0.0.1:{port}"]), d, "router"))
    try:
        with pytest.raises(zenoh.ZError, match="Unable to connect"):
            _open(tls.zenoh_tls(wire.zenoh_config("client", connect=[f"tcp/127.0.0.1:{port}"]), d, "agent-1"))
    finally:
        router.close()


# --------------------------------------------------------------------------- ACL (b)


def test_acl_agent_publishes_only_on_its_own_keys(acl_net):
    a1, a2, ns, op = (acl_net.client(n) for n in ("agent-1", "agent-2", "netsim", "operator"))
    seen, at_netsim, at_a2 = Inbox(), Inbox(), Inbox()
    op.declare_subscriber(f"{P}/**", seen)
    ns.declare_subscriber(f"{P}/radio/tx/*", at_netsim)
    a2.declare_subscriber(f"{P}/radio/rx/2", at_a2)
    a2.declare_subscriber(f"{P}/clock", at_a2)
    a2.declare_subscriber(f"{P}/agent/2/sensors", at_a2)
    _ready(a1, f"{P}/radio/tx/1", seen)
    _ready(ns, f"{P}/clock", at_a2)
    seen.items.clear()
    at_netsim.items.clear()
    at_a2.items.clear()

    denied = [f"{P}/radio/tx/2", f"{P}/netsim/control", f"{P}/clock", f"{P}/agent/2/sensors",
              f"{P}/agent/2/estimate", f"{P}/radio/rx/2", f"{P}/radio/rx/all", f"{P}/truth/1", "elsewhere/x"]
    for key in denied:
        a1.put(key, b"spoof")  # returns normally: the router drops it
    a1.put(f"{P}/agent/1/estimate", b"est")
    a1.put(f"{P}/radio/tx/1", b"frame")  # last: once it is in, anything before it would be too
    seen.wait((f"{P}/radio/tx/1", b"frame"))
    at_netsim.wait((f"{P}/radio/tx/1", b"frame"))
    time.sleep(0.2)
    assert seen.items == [(f"{P}/agent/1/estimate", b"est"), (f"{P}/radio/tx/1", b"frame")]
    assert at_netsim.items == [(f"{P}/radio/tx/1", b"frame")]
    assert at_a2.items == []

    # netsim may feed agent 2; agent 1 may not even subscribe to agent 2's sensors
    peek = Inbox()
    a1.declare_subscriber(f"{P}/agent/2/sensors", peek)
    a1.declare_subscriber(f"{P}/radio/rx/2", peek)
    time.sleep(0.2)
    ns.put(f"{P}/agent/2/sensors", b"sensors")
    ns.put(f"{P}/radio/rx/2", b"fwd")
    ns.put(f"{P}/clock", b"tick")
    fed = [(f"{P}/agent/2/sensors", b"sensors"), (f"{P}/radio/rx/2", b"fwd"), (f"{P}/clock", b"tick")]
    for item in fed:  # samples on different keys may reach the callbacks in any order
        at_a2.wait(item)
    assert sorted(at_a2.items) == sorted(fed)
    # the operator reads everything but writes nothing that reaches others
    op.put(f"{P}/clock", b"operator-tick")
    ns.put(f"{P}/clock", b"tick2")
    at_a2.wait((f"{P}/clock", b"tick2"))
    time.sleep(0.1)
    assert peek.items == []
    assert (f"{P}/clock", b"operator-tick") not in at_a2.items


def _answer(key, text):
    """A queryable's callback that replies `text` on `key` (its own key, as swarmloc's do)."""
    def on_query(query):
        query.reply(key, text.encode())
    return on_query


def _replies(session, key):
    """(key, payload) of every reply, unconsolidated."""
    rs = session.get(key, timeout=2.0, consolidation=zenoh.ConsolidationMode.NONE)
    return sorted((str(r.ok.key_expr), r.ok.payload.to_bytes()) for r in rs if r.ok is not None)


def test_acl_queries_replies_and_liveliness(acl_net):
    a1, a2, ns, op = (acl_net.client(n) for n in ("agent-1", "agent-2", "netsim", "operator"))
    control, s1, s2 = f"{P}/netsim/control", f"{P}/agent/1/stats", f"{P}/agent/2/stats"
    keep = [
        ns.declare_queryable(control, _answer(control, "netsim")),
        a1.declare_queryable(control, _answer(control, "agent-1 posing as netsim")),  # declaration denied
        a1.declare_queryable(s1, _answer(s1, "stats 1")),
        a2.declare_queryable(s2, _answer(s2, "stats 2")),
    ]
    deadline = time.monotonic() + 5
    while _replies(op, s2) != [(s2, b"stats 2")]:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert _replies(op, control) == [(control, b"netsim")]
    assert _replies(op, s1) == [(s1, b"stats 1")]
    both = [(s1, b"stats 1"), (s2, b"stats 2")]
    assert _replies(op, f"{P}/agent/*/stats") == both  # as netsim asks at the end of a run
    assert _replies(ns, f"{P}/agent/*/stats") == both
    assert _replies(a2, control) == []  # agents may not send control requests
    assert _replies(a2, s1) == []       # nor ask each other

    # An agent cannot answer for another one asked by name: the query never reaches it...
    keep.append(a1.declare_queryable(s2, _answer(s2, "agent-1 posing as 2")))
    time.sleep(0.2)
    assert _replies(op, s2) == [(s2, b"stats 2")]
    # ...but Zenoh's ACL checks a reply against the QUERY's key expression, so when asked
    # agent/*/stats (which agent-1 must be allowed to answer) its forged reply on agent/2/stats
    # gets through. Known limitation (docs/security.md): ask agent/<id>/stats by name to be sure.
    assert _replies(op, f"{P}/agent/*/stats") == sorted(both + [(s2, b"agent-1 posing as 2")])

    # liveliness: an agent holds its own token only; netsim and the operator see it
    events = Inbox()
    keep.append(op.liveliness().declare_subscriber(f"{P}/agent/*/alive", events, history=True))
    keep += [a1.liveliness().declare_token(f"{P}/agent/2/alive"),  # denied
             a1.liveliness().declare_token(f"{P}/agent/1/alive")]
    events.wait((f"{P}/agent/1/alive", b""))
    at_netsim = Inbox()
    keep.append(ns.liveliness().declare_subscriber(f"{P}/agent/*/alive", at_netsim, history=True))
    at_netsim.wait((f"{P}/agent/1/alive", b""))
    # A liveliness query right after the subscriber saw the token sometimes comes back empty,
    # with or without TLS and ACL (Zenoh 1.10.2, about 1 in 5 on loopback): ask until answered.
    deadline = time.monotonic() + 3
    while (alive := [str(r.ok.key_expr) for r in op.liveliness().get(f"{P}/agent/*/alive", timeout=1.0) if r.ok]) == []:
        assert time.monotonic() < deadline, "liveliness query never answered"
        time.sleep(0.1)
    assert alive == [f"{P}/agent/1/alive"]
    time.sleep(0.1)
    # The token may be seen twice (once from the history query, once live, when the subscriber
    # is declared while the token travels): what matters is that agent-2's forged one never is.
    assert set(events.items) == {(f"{P}/agent/1/alive", b"")} and set(at_netsim.items) == set(events.items)
    # an agent (not in direct mode) does not watch the others
    peek = Inbox()
    keep.append(a2.liveliness().declare_subscriber(f"{P}/agent/*/alive", peek, history=True))
    time.sleep(0.3)
    assert peek.items == []


def test_acl_with_netsim_as_the_router(pki):
    """swarmloc's netsim is itself the router: its own session is not subject to the ACL, the
    rules for the members still hold for what it sends them and what they send it."""
    net = Net(pki, acl=True, router_name="netsim")
    try:
        netsim = net.router
        from_agents = Inbox()
        netsim.declare_subscriber(f"{P}/radio/tx/*", from_agents)
        control = netsim.declare_queryable(f"{P}/netsim/control", _answer(f"{P}/netsim/control", "netsim"))
        a1, op = net.client("agent-1"), net.client("operator")
        clock = Inbox()
        a1.declare_subscriber(f"{P}/clock", clock)
        _ready(netsim, f"{P}/clock", clock)
        a1.put(f"{P}/radio/tx/2", b"spoof")
        a1.put(f"{P}/radio/tx/1", b"frame")
        from_agents.wait((f"{P}/radio/tx/1", b"frame"))
        assert from_agents.items == [(f"{P}/radio/tx/1", b"frame")]
        assert _replies(op, f"{P}/netsim/control") == [(f"{P}/netsim/control", b"netsim")]
        assert _replies(a1, f"{P}/netsim/control") == []
        del control
    finally:
        net.close()


def test_acl_direct_mode_lets_agents_reach_each_other(pki):
    net = Net(pki, acl=True, direct=True)
    try:
        a1, a2 = net.client("agent-1"), net.client("agent-2")
        inbox = Inbox()
        a2.declare_subscriber(f"{P}/radio/rx/2", inbox)
        a2.declare_subscriber(f"{P}/radio/rx/all", inbox)
        _ready(a1, f"{P}/radio/rx/all", inbox)
        a1.put(f"{P}/radio/rx/2", b"unicast")
        inbox.wait((f"{P}/radio/rx/2", b"unicast"))
        token = a1.liveliness().declare_token(f"{P}/agent/1/alive")
        alive = Inbox()
        sub = a2.liveliness().declare_subscriber(f"{P}/agent/*/alive", alive, history=True)
        alive.wait((f"{P}/agent/1/alive", b""))
        del token, sub
    finally:
        net.close()


def test_acl_without_client_certificate_nothing_is_allowed(pki):
    """A router that does not ask for client certificates (mutual=False) cannot tell members
    apart: a client matches no ACL subject and default deny leaves it nothing."""
    net = Net(pki, acl=True, mutual=False)
    try:
        op = net.client("operator", mutual=False)  # connects (TLS, server authenticated only)
        a1 = net.client("agent-1", mutual=False)
        inbox = Inbox()
        op.declare_subscriber(f"{P}/**", inbox)
        time.sleep(0.3)
        a1.put(f"{P}/radio/tx/1", b"frame")
        time.sleep(0.3)
        assert inbox.items == []
    finally:
        net.close()
