"""Fleet security: credentials files, ACL generation, and real Zenoh routers on 127.0.0.1 with
user/password authentication, mutual TLS and the fleet ACL.

Denied messages are dropped silently by Zenoh, so "not delivered" is tested by delivery: the
denied sample is sent first and a permitted one after it on the same session; once the permitted
one has arrived (same link, same priority: in order), the denied one must not have.
Certificates are generated at test time in temporary directories (nothing private is committed).
"""

from __future__ import annotations

import json
import os
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from agents.errors import UserError
from agents.fleet.secure import (
    CertSet,
    Credentials,
    ServerTls,
    acl_config,
    apply_credentials,
    check_private,
    client_settings,
    endpoint_address,
    endpoint_reachable,
    generate_test_certs,
    load_credentials,
    main,
    make_secure_fleet,
    parse_credentials,
    password_dictionary,
    router_config,
    to_zenoh_config,
    write_credentials,
    write_password_dictionary,
)

REPO = Path(__file__).resolve().parent.parent
SECURE = REPO / "broker_config" / "secure"
F = "wiremap/f"
WAIT = 5.0  # generous bound for a permitted sample to arrive; normally milliseconds


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# ====================================================================== pure helpers
def test_parse_credentials_resolves_paths_and_skips_comment_lines(tmp_path: Path) -> None:
    text = '// a comment\n# another\n{"user": "r1", "password": "pw", "ca": "c/ca.pem",\n "cert": "c/r1.pem", "key": "/abs/r1.key"}\n'  # noqa: E501
    c = parse_credentials(text, tmp_path)
    assert c.user == "r1" and c.password == "pw"
    assert c.ca == (tmp_path / "c" / "ca.pem").resolve()
    assert c.cert == (tmp_path / "c" / "r1.pem").resolve()
    assert c.key == Path("/abs/r1.key")
    assert "pw" not in repr(c)  # the password never reaches logs
    assert c.has_password and c.has_tls and c.has_client_cert


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('{"user": "r1"}', "both 'user' and 'password'"),
        ('{"password": "x"}', "both 'user' and 'password'"),
        ('{"cert": "a.pem", "ca": "ca.pem"}', "both 'cert' and 'key'"),
        ('{"cert": "a.pem", "key": "a.key"}', "needs 'ca'"),
        ('{"user": "r1", "password": "x", "extra": 1}', "unknown field"),
        ('{"user": 3, "password": "x"}', "must be a string"),
        ('["r1", "pw"]', "expected a JSON object"),
        ("{}", "no credentials"),
        ('{"user": "r1", "password": "x",}', "not valid JSON"),
        ('{"user": "a:b", "password": "x"}', "bad user name"),
        ('{"user": "r1", "password": ""}', "non-empty line"),
    ],
)
def test_parse_credentials_rejects(text: str, message: str) -> None:
    with pytest.raises(UserError, match=message):
        parse_credentials(text)


def test_credentials_example_is_a_valid_document() -> None:
    c = parse_credentials((SECURE / "credentials.example").read_text(), SECURE)
    assert c.user == "r1" and c.cert == (SECURE / "certs" / "r1.pem").resolve()


def test_load_credentials_refuses_a_password_file_readable_by_others(tmp_path: Path) -> None:
    p = tmp_path / "r1.json"
    p.write_text('{"user": "r1", "password": "pw"}')
    p.chmod(0o644)
    with pytest.raises(UserError, match="chmod 600"):
        load_credentials(p)
    with pytest.warns(UserWarning, match="accessible by others"):
        assert load_credentials(p, strict=False).user == "r1"
    p.chmod(0o600)
    assert load_credentials(p).password == "pw"
    with pytest.raises(UserError, match="no such file"):
        load_credentials(tmp_path / "missing.json")


def test_load_credentials_checks_the_referenced_files(tmp_path: Path) -> None:
    for name in ("ca.pem", "r1.pem", "r1.key"):
        (tmp_path / name).write_text("x")
    (tmp_path / "r1.key").chmod(0o644)
    p = tmp_path / "c.json"
    p.write_text('{"ca": "ca.pem", "cert": "r1.pem", "key": "r1.key"}')  # no password: 0644 is fine
    p.chmod(0o644)
    with pytest.raises(UserError, match="private key"):
        load_credentials(p)
    (tmp_path / "r1.key").chmod(0o600)
    assert load_credentials(p).key == (tmp_path / "r1.key").resolve()
    (tmp_path / "ca.pem").unlink()
    with pytest.raises(UserError, match="does not exist"):
        load_credentials(p)


def test_write_credentials_round_trip_is_private_and_relative(tmp_path: Path) -> None:
    (tmp_path / "certs").mkdir()
    for name in ("ca.pem", "r1.pem", "r1.key"):
        (tmp_path / "certs" / name).write_text("x")
        (tmp_path / "certs" / name).chmod(0o600)
    c = Credentials("r1", "s3cret", tmp_path / "certs/ca.pem", tmp_path / "certs/r1.pem",
                    tmp_path / "certs/r1.key")
    p = write_credentials(tmp_path / "creds" / "r1.json", c)
    assert p.stat().st_mode & 0o777 == 0o600
    assert json.loads(p.read_text())["ca"] == "../certs/ca.pem"
    assert load_credentials(p) == c


def test_client_settings() -> None:
    assert client_settings(Credentials("r1", "pw")) == {
        "transport/auth/usrpwd/user": "r1",
        "transport/auth/usrpwd/password": "pw",
    }
    tls = client_settings(Credentials(ca=Path("/c/ca.pem"), cert=Path("/c/r1.pem"), key=Path("/c/r1.key")))
    assert tls == {
        "transport/link/tls/root_ca_certificate": "/c/ca.pem",
        "transport/link/tls/connect_certificate": "/c/r1.pem",
        "transport/link/tls/connect_private_key": "/c/r1.key",
        "transport/link/tls/enable_mtls": True,
    }
    cfg = apply_credentials(zenoh.Config(), Credentials("r1", "pw", ca=Path("/c/ca.pem")))
    assert json.loads(cfg.get_json("transport/auth/usrpwd/user")) == "r1"
    assert json.loads(cfg.get_json("transport/link/tls/root_ca_certificate")) == "/c/ca.pem"


def test_password_dictionary(tmp_path: Path) -> None:
    assert password_dictionary({"r2": "b", "fusion": "a=b", "r1": "x y"}) == "fusion:a=b\nr1:x y\nr2:b\n"
    for bad in ({"a:b": "x"}, {"": "x"}, {"r1": "two\nlines"}, {"r1": ""}):
        with pytest.raises(UserError):
            password_dictionary(bad)
    p = write_password_dictionary(tmp_path / "pw.txt", {"r1": "x"})
    assert p.stat().st_mode & 0o777 == 0o600 and p.read_text() == "r1:x\n"
    check_private(p)


def _policy_map(acl: dict[str, Any]) -> dict[str, set[tuple[str, str, str]]]:
    """subject id -> {(message, flow, key_expr)} it is allowed."""
    rules = {r["id"]: r for r in acl["rules"]}
    out: dict[str, set[tuple[str, str, str]]] = {}
    for pol in acl["policies"]:
        for s in pol["subjects"]:
            for rid in pol["rules"]:
                r = rules[rid]
                assert r["permission"] == "allow"
                out.setdefault(s, set()).update(
                    (m, f, k) for m in r["messages"] for f in r["flows"] for k in r["key_exprs"]
                )
    return out


def test_acl_config_grants() -> None:
    acl = acl_config("f", ["r1", "r2"], observers=["monitor"])
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    grants = _policy_map(acl)
    assert grants["robot-r1"] == {
        ("put", "ingress", "wiremap/f/robots/r1/**"),
        ("delete", "ingress", "wiremap/f/robots/r1/**"),
        ("liveliness_token", "ingress", "wiremap/f/alive/r1"),
    }
    writes_fused = {s for s, g in grants.items() if ("put", "ingress", "wiremap/f/fused/**") in g}
    assert writes_fused == {"fusion"}
    assert ("declare_queryable", "ingress", "wiremap/f/fused/**") in grants["fusion"]
    assert ("declare_subscriber", "ingress", "wiremap/f/robots/**") in grants["observer-monitor"]
    # admin/** (wiremap fleet forget): only the fusion identity asks and answers
    asks_admin = {
        s for s, g in grants.items() if any(m == "query" and k.startswith("wiremap/f/admin") for m, _, k in g)
    }
    assert asks_admin == {"fusion"}
    assert ("declare_queryable", "ingress", "wiremap/f/admin/**") in grants["fusion"]
    assert not any("/**" == k[-3:] and k == "wiremap/f/**" for g in grants.values() for _, _, k in g)
    assert not any(
        m in ("put", "delete", "declare_queryable") and f == "ingress"
        for m, f, _ in grants["observer-monitor"]
    )
    assert ("declare_subscriber", "ingress", "wiremap/f/fused/**") in grants["any"]
    assert ("query", "ingress", "wiremap/f/fused/**") in grants["any"]
    assert not any(f == "ingress" and m in ("put", "delete", "liveliness_token") for m, f, _ in grants["any"])
    subjects = {s["id"]: s for s in acl["subjects"]}
    assert subjects["any"] == {"id": "any"}
    assert subjects["robot-r2"] == {"id": "robot-r2", "usernames": ["r2"]}


def test_acl_config_fusion_tree_grants() -> None:
    """A regional fuser writes only its group's keys and token; the root (the fusion identity)
    reads the partials and declares the root tokens; robots gain nothing."""
    acl = acl_config("f", ["r1", "r2"], observers=["monitor"], fusers=["g0", "g1"])
    grants = _policy_map(acl)
    writes = {s: {(m, k) for m, f, k in g if f == "ingress" and m in ("put", "delete", "declare_queryable",
                                                                       "reply", "liveliness_token")}
              for s, g in grants.items()}
    assert writes["fuser-g0"] == {
        ("put", "wiremap/f/groups/g0/**"), ("delete", "wiremap/f/groups/g0/**"),
        ("declare_queryable", "wiremap/f/groups/g0/**"), ("reply", "wiremap/f/groups/g0/**"),
        ("liveliness_token", "wiremap/f/fusers/g0"),
    }  # fmt: skip
    assert ("declare_subscriber", "ingress", "wiremap/f/robots/**") in grants["fuser-g0"]
    assert ("declare_subscriber", "ingress", "wiremap/f/groups/**") in grants["fuser-g0"]
    assert ("query", "egress", "wiremap/f/groups/g0/**") in grants["fuser-g0"]
    assert not any(k.startswith("wiremap/f/groups/g1") for _, _, k in grants["fuser-g0"])
    assert ("declare_subscriber", "ingress", "wiremap/f/groups/**") in grants["fusion"]
    assert ("liveliness_token", "ingress", "wiremap/f/fusers/root/*") in grants["fusion"]
    assert ("put", "ingress", "wiremap/f/fused/**") in grants["fusion"]
    for s in ("robot-r1", "observer-monitor", "fuser-g0", "fuser-g1"):
        assert not any(m == "put" and k.startswith("wiremap/f/fused") and f == "ingress"
                       for m, f, k in grants[s]), s
    assert writes["robot-r1"] == {("put", "wiremap/f/robots/r1/**"), ("delete", "wiremap/f/robots/r1/**"),
                                  ("liveliness_token", "wiremap/f/alive/r1")}
    assert writes["observer-monitor"] == set()
    both = {s["id"]: s for s in acl_config("f", ["r1"], identity="both", fusers=["g0"])["subjects"]}
    assert both["fuser-g0"] == {"id": "fuser-g0", "usernames": ["fuser-g0"],
                                "cert_common_names": ["fuser-g0"]}
    assert "fuser-g0" in next(p for p in acl_config("f", ["r1"], identity="both", fusers=["g0"])["policies"]
                              if p["id"] == "any")["subjects"]
    # without a tree nothing of it is granted
    assert not any("groups" in k or "fusers" in k for g in _policy_map(acl_config("f", ["r1"])).values()
                   for _, _, k in g)
    with pytest.raises(UserError, match="reserved"):
        acl_config("f", ["r1"], fusers=["root"])
    with pytest.raises(UserError, match="used twice"):
        acl_config("f", ["fuser-g0"], fusers=["g0"])


def test_acl_config_identity_kinds_and_errors() -> None:
    by_cert = {s["id"]: s for s in acl_config("f", ["r1"], identity="cert")["subjects"]}
    assert by_cert["robot-r1"] == {"id": "robot-r1", "cert_common_names": ["r1"]}
    both = {s["id"]: s for s in acl_config("f", ["r1"], "fz", identity="both")["subjects"]}
    assert both["fusion"] == {"id": "fusion", "usernames": ["fz"], "cert_common_names": ["fz"]}
    with pytest.raises(UserError, match="used twice"):
        acl_config("f", ["r1", "r1"])
    with pytest.raises(UserError, match="used twice"):
        acl_config("f", ["fusion"])
    with pytest.raises(UserError, match="bad robot id"):
        acl_config("f", ["r/1"])
    with pytest.raises(UserError, match="bad fleet"):
        acl_config("f/**", ["r1"])
    with pytest.raises(UserError, match="identity kind"):
        acl_config("f", ["r1"], identity="token")  # type: ignore[arg-type]


@settings(max_examples=40, deadline=None)
@given(
    fleet=st.from_regex(r"[a-z][a-z0-9]{0,8}", fullmatch=True),
    robots=st.lists(st.from_regex(r"r[0-9]{1,3}", fullmatch=True), min_size=1, max_size=8, unique=True),
)
def test_acl_config_property_robot_writes_only_its_own_keys(fleet: str, robots: list[str]) -> None:
    acl = acl_config(fleet, robots)
    grants = _policy_map(acl)
    assert len({r["id"] for r in acl["rules"]}) == len(acl["rules"])
    assert len({s["id"] for s in acl["subjects"]}) == len(acl["subjects"])
    for r in robots:
        puts = {k for m, f, k in grants[f"robot-{r}"] if m == "put" and f == "ingress"}
        assert puts == {f"wiremap/{fleet}/robots/{r}/**"}
        tokens = {k for m, f, k in grants[f"robot-{r}"] if m == "liveliness_token"}
        assert tokens == {f"wiremap/{fleet}/alive/{r}"}


def test_endpoint_address_and_reachable() -> None:
    assert endpoint_address("tcp/127.0.0.1:7447") == ("127.0.0.1", 7447)
    assert endpoint_address("tls/localhost:7448") == ("localhost", 7448)
    assert endpoint_address("tcp/[::1]:7447") == ("::1", 7447)
    assert endpoint_address("tls/localhost:7447?x=1") == ("localhost", 7447)
    assert endpoint_address("udp/127.0.0.1:7447") is None
    assert endpoint_address("nonsense") is None
    assert endpoint_reachable(f"tcp/127.0.0.1:{free_port()}", timeout=0.2) is False


def test_router_config_shape(tmp_path: Path) -> None:
    tls = ServerTls(tmp_path / "ca.pem", tmp_path / "s.pem", tmp_path / "s.key")
    doc = router_config(["tls/localhost:1"], dictionary_file=tmp_path / "pw.txt", tls=tls,
                        acl={"enabled": True})
    assert doc["mode"] == "router" and doc["scouting"]["multicast"]["enabled"] is False
    assert doc["transport"]["auth"]["usrpwd"]["dictionary_file"] == str(tmp_path / "pw.txt")
    assert doc["transport"]["link"]["tls"]["enable_mtls"] is True
    assert doc["access_control"] == {"enabled": True}
    plain = router_config(["tcp/127.0.0.1:1"])
    assert "transport" not in plain and "access_control" not in plain
    with pytest.raises(UserError):
        to_zenoh_config({"mode": "nonsense-mode"})


@pytest.mark.parametrize(("name", "identity"), [("usrpwd", "username"), ("mtls", "cert"), ("secure", "both")])
def test_committed_router_files_match_acl_config(name: str, identity: str) -> None:
    cfg = zenoh.Config.from_file(str(SECURE / f"router-{name}.json5"))
    want = to_zenoh_config(
        {
            "access_control": acl_config(
                "default", ["r1", "r2", "r3"], observers=["monitor"], identity=identity, fusers=["g0", "g1"]
            )
        }  # type: ignore[arg-type]
    )
    assert json.loads(cfg.get_json("access_control")) == json.loads(want.get_json("access_control"))
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    has_pw = json.loads(cfg.get_json("transport/auth/usrpwd/dictionary_file")) is not None
    assert has_pw == (name in ("usrpwd", "secure"))


def test_committed_acl_fragment_matches_acl_config() -> None:
    text = (SECURE / "acl.json5").read_text()
    cfg = zenoh.Config.from_json5(
        "{access_control: " + "\n".join(ln for ln in text.splitlines() if not ln.startswith("//")) + "}"
    )
    want = to_zenoh_config({"access_control": acl_config("default", ["r1", "r2", "r3"],
                                                         observers=["monitor"], fusers=["g0", "g1"])})
    assert json.loads(cfg.get_json("access_control")) == json.loads(want.get_json("access_control"))


def test_no_private_material_committed() -> None:
    for p in SECURE.rglob("*"):
        if p.is_file() and p.name != ".gitignore":
            assert "PRIVATE KEY" not in p.read_text(errors="replace"), p


# ====================================================================== certificates
@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> CertSet:
    return generate_test_certs(tmp_path_factory.mktemp("certs"), ["r1", "r2", "fusion", "viewer"])


@pytest.fixture(scope="module")
def foreign_certs(tmp_path_factory: pytest.TempPathFactory) -> CertSet:
    return generate_test_certs(tmp_path_factory.mktemp("foreign"), ["r1"])


def _openssl(*args: str) -> str:
    return subprocess.run(["openssl", *args], check=True, capture_output=True, text=True).stdout


@pytest.mark.fleet
def test_generated_certificates(certs: CertSet, foreign_certs: CertSet) -> None:
    text = _openssl("x509", "-in", str(certs.server.cert), "-noout", "-ext", "subjectAltName")
    assert "DNS:localhost" in text and "IP Address:127.0.0.1" in text
    subject = _openssl("x509", "-in", str(certs.clients["r1"][0]), "-noout", "-subject").replace(" ", "")
    assert subject.strip() == "subject=CN=r1"
    for pem in (certs.server.cert, certs.clients["r2"][0]):
        assert _openssl("verify", "-CAfile", str(certs.ca), str(pem)).strip().endswith("OK")
    bad = subprocess.run(
        ["openssl", "verify", "-CAfile", str(certs.ca), str(foreign_certs.clients["r1"][0])],
        capture_output=True
    )
    assert bad.returncode != 0
    for key in (certs.ca_key, certs.server.key, *(k for _, k in certs.clients.values())):
        assert key.stat().st_mode & 0o777 == 0o600


# ====================================================================== live routers
def _client(endpoint: str, creds: Credentials | None) -> zenoh.Config:
    cfg = to_zenoh_config(
        {"mode": "client", "connect": {"endpoints": [endpoint]},
         "scouting": {"multicast": {"enabled": False}}}
    )
    return apply_credentials(cfg, creds) if creds is not None else cfg


class Inbox:
    """Samples (key, payload) received by a callback, with an event per awaited payload."""

    def __init__(self) -> None:
        self.items: list[tuple[str, bytes]] = []
        self.cond = threading.Condition()

    def __call__(self, sample: Any) -> None:
        with self.cond:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))
            self.cond.notify_all()

    def wait_for(self, pred: Callable[[tuple[str, bytes]], bool], timeout: float = WAIT) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: any(pred(i) for i in self.items), timeout)

    def payloads(self) -> list[bytes]:
        with self.cond:
            return [p for _, p in self.items]


def _put_until_seen(sess: zenoh.Session, key: str, inbox: Inbox, tag: bytes, timeout: float = WAIT) -> None:
    """Put ``tag`` on ``key`` until ``inbox`` has it: waits for a subscription to propagate."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        sess.put(key, tag)
        if inbox.wait_for(lambda i: i[1] == tag, 0.1):
            return
    raise AssertionError(f"{tag!r} on {key} never arrived")


@contextmanager
def _router(doc: dict[str, Any]) -> Iterator[zenoh.Session]:
    with zenoh.open(to_zenoh_config(doc)) as session:
        yield session


@pytest.fixture(scope="module")
def usrpwd_router(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, dict[str, Credentials]]]:
    d = tmp_path_factory.mktemp("usrpwd")
    users = {"r1": "pw-r1", "r2": "pw-r2", "fusion": "pw-fusion", "viewer": "pw-viewer"}
    dictionary = write_password_dictionary(d / "passwords.txt", users)
    ep = f"tcp/127.0.0.1:{free_port()}"
    doc = router_config([ep], dictionary_file=dictionary, acl=acl_config("f", ["r1", "r2"]))
    with _router(doc):
        yield ep, {u: Credentials(u, pw) for u, pw in users.items()}


@pytest.fixture(scope="module")
def mtls_router(certs: CertSet) -> Iterator[str]:
    ep = f"tls/localhost:{free_port()}"
    doc = router_config([ep], tls=certs.server, acl=acl_config("f", ["r1", "r2"], identity="cert"))
    with _router(doc):
        yield ep


def _refused(cfg: zenoh.Config) -> bool:
    try:
        s = zenoh.open(cfg)
    except zenoh.ZError:
        return True
    s.close()
    return False


@pytest.mark.fleet
def test_usrpwd_wrong_or_missing_password_is_refused(
    usrpwd_router: tuple[str, dict[str, Credentials]],
) -> None:
    ep, creds = usrpwd_router
    assert _refused(_client(ep, Credentials("r1", "wrong")))
    assert _refused(_client(ep, Credentials("intruder", "pw-r1")))
    assert _refused(_client(ep, None))  # unauthenticated: no session, so it receives nothing
    with zenoh.open(_client(ep, creds["r1"])) as s:
        assert str(s.zid())
    # a refusal looks like "no router" to zenoh.open; the TCP probe tells them apart
    assert endpoint_reachable(ep)


def _query_fused(sess: zenoh.Session) -> list[bytes]:
    """Query the fused map (every matching queryable: target ALL) until a reply comes (the
    queryable may still be propagating); sorted payloads of the replies."""
    got: list[bytes] = []
    deadline = time.monotonic() + WAIT
    while not got and time.monotonic() < deadline:
        replies = sess.get(f"{F}/fused/map", target=zenoh.QueryTarget.ALL, timeout=1.0)
        got = sorted(r.ok.payload.to_bytes() for r in replies if r.ok)
    return got


def _check_fleet_acl(ep: str, creds: dict[str, Credentials]) -> None:
    """The ACL delivery checks shared by the usrpwd, mTLS and generated-fleet routers
    (``creds`` has r1, r2, fusion and viewer; viewer is a plain authenticated client)."""
    with ExitStack() as stack:
        fusion = stack.enter_context(zenoh.open(_client(ep, creds["fusion"])))
        r1 = stack.enter_context(zenoh.open(_client(ep, creds["r1"])))
        r2 = stack.enter_context(zenoh.open(_client(ep, creds["r2"])))
        viewer = stack.enter_context(zenoh.open(_client(ep, creds["viewer"])))
        maps, fused_at_r1, fused_at_viewer, alive, r1_spy = Inbox(), Inbox(), Inbox(), Inbox(), Inbox()
        ents: list[Any] = [
            fusion.declare_subscriber(f"{F}/robots/*/map", maps),
            r1.declare_subscriber(f"{F}/fused/map", fused_at_r1),
            viewer.declare_subscriber(f"{F}/fused/map", fused_at_viewer),
            r1.declare_subscriber(f"{F}/robots/r2/**", r1_spy),  # robots may not read each other
            fusion.liveliness().declare_subscriber(f"{F}/alive/*", alive, history=True),
            fusion.declare_queryable(f"{F}/fused/map", lambda q: q.reply(f"{F}/fused/map", b"fused-v1"),
                                     complete=True),
        ]
        try:
            _put_until_seen(r1, f"{F}/robots/r1/map", maps, b"r1-probe")
            # r1 on r2's key and on the fused key, then a permitted put on the same session:
            # once that one has arrived, the denied ones would have arrived before it
            r1.put(f"{F}/robots/r2/map", b"r1-as-r2")
            r1.put(f"{F}/fused/map", b"r1-forged-fused")
            r1.put(f"{F}/robots/r1/map", b"r1-after")
            assert maps.wait_for(lambda i: i == (f"{F}/robots/r1/map", b"r1-after"))
            assert b"r1-as-r2" not in maps.payloads()
            # r2 on its own key reaches fusion (but not r1's subscription on r2's keys, below)
            r2.put(f"{F}/robots/r2/map", b"r2-map")
            assert maps.wait_for(lambda i: i == (f"{F}/robots/r2/map", b"r2-map"))
            # fusion publishes the fused map (after it saw r2-map, so the router forwarded r2-map
            # to every allowed subscriber before this): robot and plain viewer get it
            _put_until_seen(fusion, f"{F}/fused/map", fused_at_viewer, b"fused-probe")
            fusion.put(f"{F}/fused/map", b"fused-v1")
            assert fused_at_viewer.wait_for(lambda i: i[1] == b"fused-v1")
            assert fused_at_r1.wait_for(lambda i: i[1] == b"fused-v1")
            assert b"r1-forged-fused" not in fused_at_viewer.payloads()
            assert b"r2-map" not in r1_spy.payloads()
            # liveliness: r1 may declare only its own token (declared second, seen alone)
            ents.append(r1.liveliness().declare_token(f"{F}/alive/r2"))
            ents.append(r1.liveliness().declare_token(f"{F}/alive/r1"))
            assert alive.wait_for(lambda i: i[0] == f"{F}/alive/r1")
            assert [k for k, _ in alive.items] == [f"{F}/alive/r1"]
            # a robot and a viewer query the fused map and get the fusion service's reply
            assert _query_fused(r1) == [b"fused-v1"]
            assert _query_fused(viewer) == [b"fused-v1"]
            # a robot cannot declare a queryable on the fused map: the viewer hears only fusion
            ents.append(r1.declare_queryable(f"{F}/fused/map", lambda q: q.reply(f"{F}/fused/map", b"fake"),
                                             complete=True))
            _put_until_seen(r1, f"{F}/robots/r1/map", maps, b"r1-after-queryable")  # declaration sent before
            assert _query_fused(viewer) == [b"fused-v1"]
        finally:
            for e in reversed(ents):
                e.undeclare()


@pytest.mark.fleet
def test_usrpwd_acl_delivery(usrpwd_router: tuple[str, dict[str, Credentials]]) -> None:
    ep, creds = usrpwd_router
    _check_fleet_acl(ep, creds)


@pytest.mark.fleet
def test_usrpwd_liveliness_only_own_token_put_and_delete(
    usrpwd_router: tuple[str, dict[str, Credentials]],
) -> None:
    ep, creds = usrpwd_router
    with zenoh.open(_client(ep, creds["viewer"])) as viewer, zenoh.open(_client(ep, creds["r2"])) as r2:
        alive = Inbox()
        sub = viewer.liveliness().declare_subscriber(f"{F}/alive/*", alive, history=True)
        tok_fake = r2.liveliness().declare_token(f"{F}/alive/r1")
        tok = r2.liveliness().declare_token(f"{F}/alive/r2")
        try:
            assert alive.wait_for(lambda i: i[0] == f"{F}/alive/r2")
            tok.undeclare()  # and the DELETE of a legitimate token gets through
            with alive.cond:
                assert alive.cond.wait_for(lambda: len(alive.items) >= 2, WAIT)
            assert [k for k, _ in alive.items] == [f"{F}/alive/r2", f"{F}/alive/r2"]
        finally:
            tok_fake.undeclare()
            sub.undeclare()


@pytest.mark.fleet
def test_mtls_refuses_missing_or_foreign_certificate(
    mtls_router: str, certs: CertSet, foreign_certs: CertSet
) -> None:
    ep = mtls_router
    assert _refused(_client(ep, Credentials(ca=certs.ca)))  # server verified, no client certificate
    assert _refused(_client(ep, None))
    assert _refused(_client(ep, foreign_certs.client_credentials("r1")))  # signed by another CA
    with zenoh.open(_client(ep, certs.client_credentials("r1"))) as s:
        assert str(s.zid())
    assert endpoint_reachable(ep)


@pytest.mark.fleet
def test_mtls_acl_by_certificate_common_name(mtls_router: str, certs: CertSet) -> None:
    _check_fleet_acl(mtls_router, {n: certs.client_credentials(n) for n in ("r1", "r2", "fusion", "viewer")})


@pytest.mark.fleet
def test_generated_secure_fleet_end_to_end(tmp_path: Path) -> None:
    """make_secure_fleet: usrpwd AND mTLS; the ACL needs user name = CN, so a robot with its own
    password but another robot's certificate gets nothing through."""
    ep = f"tls/localhost:{free_port()}"
    fl = make_secure_fleet(tmp_path / "sec", "f", ["r1", "r2"], observers=["viewer"], listen=ep)
    assert set(fl.credentials) == {"fusion", "viewer", "r1", "r2"}
    for p in [*fl.credentials.values(), fl.directory / "passwords.txt"]:
        assert p.stat().st_mode & 0o777 == 0o600
    creds = {i: load_credentials(p) for i, p in fl.credentials.items()}
    assert creds["r1"].has_password and creds["r1"].has_client_cert
    with _router(fl.router):
        assert _refused(_client(ep,
                                Credentials("r1", "wrong", creds["r1"].ca, creds["r1"].cert,
                                            creds["r1"].key)))
        assert _refused(
            _client(ep, Credentials("r1", creds["r1"].password, creds["r1"].ca))
        )  # no certificate
        _check_fleet_acl(ep, creds)
        mixed = Credentials("r1", creds["r1"].password, creds["r2"].ca, creds["r2"].cert, creds["r2"].key)
        with (
            zenoh.open(_client(ep, creds["fusion"])) as fusion,
            zenoh.open(_client(ep, mixed)) as m,
            zenoh.open(_client(ep, creds["r1"])) as r1,
        ):
            maps = Inbox()
            sub = fusion.declare_subscriber(f"{F}/robots/*/map", maps)
            try:
                _put_until_seen(r1, f"{F}/robots/r1/map", maps, b"probe")
                m.put(f"{F}/robots/r1/map", b"mixed-r1")
                m.put(f"{F}/robots/r2/map", b"mixed-r2")
                r1.put(f"{F}/robots/r1/map", b"after")
                assert maps.wait_for(lambda i: i[1] == b"after")
                time.sleep(0.1)  # m and r1 are different links: leave m's puts time to arrive
                assert not {b"mixed-r1", b"mixed-r2"} & set(maps.payloads())
            finally:
                sub.undeclare()


def test_cli_init_writes_a_fleet_and_refuses_to_overwrite(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    d = tmp_path / "fleet"
    assert main(["init", str(d), "--robots", "a1", "--no-mtls", "--listen", "tcp/127.0.0.1:7447"]) == 0
    assert "--credentials" in capsys.readouterr().out
    assert (d / "passwords.txt").read_text().count("\n") == 3  # fusion, monitor, a1
    assert not (d / "certs").exists()
    assert main(["init", str(d), "--robots", "a1"]) == 2
    assert "already holds credentials" in capsys.readouterr().err
    assert main(["init", str(d / "x"), "--robots", "a1", "--no-usrpwd", "--no-mtls"]) == 2


def test_fusion_drops_a_map_whose_sender_does_not_match_its_key() -> None:
    """The payload check behind the ACL: r1 may put on robots/r1/map, but an envelope saying
    "r2" there is counted and dropped by the fusion service."""
    fusion = pytest.importorskip("agents.fleet.fusion")
    import numpy as np

    from mapping.se2 import Pose
    from mapping.wireframe import Wireframe
    from wire_codec.message import MapMessage, MessageKind

    wf = Wireframe.build(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]), np.array([[0, 1], [1, 2]]))
    msg = MapMessage(
        kind=MessageKind.ROBOT_MAP, sender="r2", seq=1, stamp_ns=1, pose=Pose.identity(), frame="odom/r2",
        origin=Pose.identity(), resolution=0.05, wireframe=wf, meta={"boot": 1},
    )
    data = fusion.encode_message(msg)
    st = fusion.FusionState()
    assert st.offer(data, "r1") is False
    assert st.stats.rejected == 1 and "r2" not in st.robots and "r1" not in st.robots
    assert st.offer(data, "r2") is True


def test_check_private_without_strict_warns(tmp_path: Path) -> None:
    p = tmp_path / "k"
    p.write_text("x")
    os.chmod(p, 0o640)
    with pytest.raises(UserError, match="mode 640"):
        check_private(p, "key")
    with pytest.warns(UserWarning):
        check_private(p, "key", strict=False)


@pytest.mark.fleet
def test_committed_secure_router_runs_with_init_output(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """router-secure.json5 reads broker_config/secure/... relative to the working directory:
    ``init`` there, start the committed file (on a free port), connect robot r1."""
    monkeypatch.chdir(tmp_path)
    assert main(["init", "broker_config/secure", "--robots", "r1,r2,r3"]) == 0
    cfg = zenoh.Config.from_file(str(SECURE / "router-secure.json5"))
    ep = f"tls/localhost:{free_port()}"
    cfg.insert_json5("listen/endpoints", json.dumps([ep]))
    with zenoh.open(cfg):
        creds = load_credentials("broker_config/secure/credentials/r1.json")
        with zenoh.open(_client(ep, creds)) as s:
            assert str(s.zid())
        assert _refused(_client(ep, Credentials("r1", "wrong", creds.ca, creds.cert, creds.key)))
