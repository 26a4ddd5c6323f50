"""Fleet security: credentials files, user/password authentication, mutual TLS and access control.

Pure helpers (no session is opened here); ``agents/fleet/bus.py`` and the commands wire them in.

Threat model and choices
------------------------
* **Authentication** at connect time, by the router: a user/password dictionary
  (``transport/auth/usrpwd``) and/or mutual TLS (``tls/host:port`` endpoints, client
  certificates signed by the fleet CA). A client that fails either is refused at ``zenoh.open``:
  it never receives anything.
* **Authorisation** by the router's access-control list (:func:`acl_config`), default *deny*:

  ========================  ===============================================================
  who                       may
  ========================  ===============================================================
  robot ``ID``              put/delete under ``wiremap/<fleet>/robots/ID/**``; declare the
                            liveliness token ``wiremap/<fleet>/alive/ID`` (and no other)
  the fusion identity       put/delete, declare a queryable and reply under
                            ``wiremap/<fleet>/fused/**``; read the whole fleet (subscribe,
                            query, liveliness) and receive the queries for the fused map;
                            it is also the admin: the only one to ask and answer
                            ``wiremap/<fleet>/admin/**`` (``wiremap fleet forget ID``)
  observers (optional)      read ``robots/``, ``alive/`` and ``fused/`` (``wiremap watch``,
                            the ``wiremap run`` supervisor): no puts, no admin queries
  any authenticated client  subscribe to and query ``wiremap/<fleet>/fused/**``; see the
                            liveliness tokens ``wiremap/<fleet>/alive/**`` (``wiremap watch``
                            counts the robots alive: the ids are not secret)
  regional fuser ``NAME``   (a fusion tree, ``fusers=``; identity ``fuser-NAME``) read the
                            fleet and the tree (``groups/**``, the tokens ``fusers/**``); put,
                            declare a queryable and reply under ``wiremap/<fleet>/groups/NAME/**``
                            (its partial map and counters) and receive the queries for them;
                            declare the token ``wiremap/<fleet>/fusers/NAME`` (and no other)
  the fusion identity,      as above, and read ``groups/**`` and ``fusers/**``; declare the
  as a tree's root          tokens ``fusers/root`` and ``fusers/root/<boot>``
  ========================  ===============================================================

  A regional fuser may not publish another group's partial, so a secure tree has no standby
  takeover (``wiremap run --secure --fusers K`` passes ``--no-standby``): a dead fuser's group
  stays in the fused map as its last partial until the fuser is restarted (from its store).

  An identity is a user name (``identity="username"``), a certificate common name
  (``"cert"``) or both at once (``"both"``: the subject requires the user name *and* the
  certificate CN to equal the id -- Zenoh ANDs the properties of one subject). "Any
  authenticated client" is a subject without properties: on a router that authenticates every
  link, everyone connected is authenticated. Denied messages are dropped **silently** by Zenoh.
* Zenoh checks who may *put* on a key, not what the payload claims: the fusion service also
  drops a map whose envelope ``sender`` differs from the ``robots/<id>`` of its key.

Credentials file (one per process; never a password on the command line)
-----------------------------------------------------------------------
A JSON object; every field is optional but at least one must be present::

    // wiremap credentials for robot r1
    {"user": "r1", "password": "...", "ca": "certs/ca.pem",
     "cert": "certs/r1.pem", "key": "certs/r1.key"}

* ``user`` + ``password``: user/password authentication (both or neither).
* ``ca``: the CA that signed the router's certificate (needed for ``tls/`` endpoints).
* ``cert`` + ``key``: this process's client certificate for mutual TLS (both or neither;
  they need ``ca``).
* Relative paths are relative to the credentials file's directory.
* "JSON5-ish": whole lines starting with ``//`` or ``#`` are comments; otherwise strict JSON
  (no trailing commas, double quotes).
* Permissions (choice: *refuse*, like ``ssh`` with private keys): a credentials file holding a
  password, and a private key file, must not be readable by group or others (``chmod 600``);
  :func:`load_credentials` raises :class:`~agents.errors.UserError` otherwise
  (``strict=False`` only warns, for tests or platforms without POSIX modes).

Certificates for tests and demos come from the ``openssl`` command-line tool
(:func:`generate_test_certs`): an EC P-256 CA, a server certificate with
``subjectAltName = DNS:localhost, IP:127.0.0.1`` and one client certificate per identity with
``CN = id``. :func:`make_secure_fleet` writes everything a fleet needs in one directory;
``python -m agents.fleet.secure init DIR --fleet F --robots r1,r2`` does the same from a shell.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from agents.errors import UserError
from agents.files.io import write_atomic
from agents.fleet.bus import valid_name

if TYPE_CHECKING:
    import zenoh

Identity = Literal["username", "cert", "both"]
_FIELDS = ("user", "password", "ca", "cert", "key")
DEFAULT_SECURE_PORT = 7447
DEFAULT_FUSION_USER = "fusion"
DEFAULT_OBSERVER = "monitor"


def _check_id(name: object, what: str) -> str:
    # the rule of agents.fleet.bus.check_name (one key chunk); it also keeps ':' and newlines
    # out of the password dictionary and '/' out of certificate file names
    if not valid_name(name):
        raise UserError(f"bad {what} {name!r}: use 1-63 letters, digits, '_', '.', '-'")
    return str(name)


# ---------------------------------------------------------------------- private files
def write_private(path: str | os.PathLike[str], data: bytes | str) -> Path:
    """Write ``data`` to ``path`` atomically with mode 0600 (owner read/write only).

    The temporary file is created 0600 by ``mkstemp`` and keeps that mode, so the secret is never
    readable by others, not even for a moment.
    """
    path = Path(path)
    write_atomic(path, data, mode=0o600)
    return path


def check_private(path: str | os.PathLike[str], what: str = "file", strict: bool = True) -> None:
    """Refuse (``strict``) or warn about a secret file readable or writable by group or others.

    Raises
    ------
    UserError
        When ``strict`` and ``mode & 0o077`` is not zero. Without POSIX modes (Windows) nothing
        is checked.
    """
    if os.name != "posix":
        return
    try:
        mode = os.stat(path).st_mode & 0o777
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    if mode & 0o077:
        text = f"{what} {path} is accessible by others (mode {mode:03o}): run chmod 600 {path}"
        if strict:
            raise UserError(text)
        warnings.warn(text, stacklevel=2)


# ---------------------------------------------------------------------- credentials
@dataclass(frozen=True)
class Credentials:
    """What one process presents to the router. Paths are absolute after loading.

    The password never appears in ``repr`` (so not in logs or tracebacks).
    """

    user: str | None = None
    password: str | None = field(default=None, repr=False)
    ca: Path | None = None
    cert: Path | None = None
    key: Path | None = None

    def __post_init__(self) -> None:
        if (self.user is None) != (self.password is None):
            raise UserError("credentials: give both 'user' and 'password', or neither")
        if (self.cert is None) != (self.key is None):
            raise UserError("credentials: give both 'cert' and 'key', or neither")
        if self.cert is not None and self.ca is None:
            raise UserError("credentials: a client certificate needs 'ca' (the fleet CA)")
        if self.user is not None and (not self.user or any(c in self.user for c in ":\n\r")):
            raise UserError(f"credentials: bad user name {self.user!r}")
        if self.password is not None and (not self.password or any(c in self.password for c in "\n\r")):
            raise UserError("credentials: the password must be one non-empty line")

    @property
    def has_password(self) -> bool:
        return self.user is not None

    @property
    def has_tls(self) -> bool:
        return self.ca is not None

    @property
    def has_client_cert(self) -> bool:
        return self.cert is not None

    def to_json(self, relative_to: str | os.PathLike[str] | None = None) -> dict[str, str]:
        """The credentials-file object; paths relative to ``relative_to`` when given."""
        out: dict[str, str] = {}
        for name in _FIELDS:
            v = getattr(self, name)
            if v is None:
                continue
            if isinstance(v, Path) and relative_to is not None:
                v = os.path.relpath(v, relative_to)
            out[name] = str(v)
        return out


def parse_credentials(
    text: str, base: str | os.PathLike[str] = ".", source: str = "credentials"
) -> Credentials:
    """Parse a credentials document (see the module docstring); paths are resolved against ``base``.

    Raises
    ------
    UserError
        On malformed JSON, unknown fields, non-string values or an inconsistent set of fields.
    """
    body = "\n".join("" if ln.lstrip().startswith(("//", "#")) else ln for ln in text.splitlines())
    try:
        doc = json.loads(body)
    except json.JSONDecodeError as exc:
        raise UserError(f"{source}: not valid JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise UserError(f"{source}: expected a JSON object with {', '.join(_FIELDS)}")
    unknown = sorted(set(doc) - set(_FIELDS))
    if unknown:
        raise UserError(f"{source}: unknown field(s) {', '.join(unknown)} (known: {', '.join(_FIELDS)})")
    if not doc:
        raise UserError(f"{source}: no credentials in it")
    for k, v in doc.items():
        if not isinstance(v, str):
            raise UserError(f"{source}: {k!r} must be a string")
    paths = {k: (Path(base) / doc[k]).resolve() if k in doc else None for k in ("ca", "cert", "key")}
    try:
        return Credentials(user=doc.get("user"), password=doc.get("password"), **paths)
    except UserError as exc:
        raise UserError(f"{source}: {str(exc).removeprefix('credentials: ')}") from None


def load_credentials(path: str | os.PathLike[str], strict: bool = True) -> Credentials:
    """Read a credentials file.

    Parameters
    ----------
    path : the file (format in the module docstring).
    strict : refuse (True) or only warn about (False) a password file or a private key that
        group or others can read.

    Raises
    ------
    UserError
        A missing or unreadable file, a bad document, a missing certificate/key/CA file, or
        (``strict``) a secret readable by others.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read: {exc}") from None
    creds = parse_credentials(text, p.resolve().parent, str(path))
    if creds.has_password:
        check_private(p, "credentials file", strict)
    for name in ("ca", "cert", "key"):
        f = getattr(creds, name)
        if f is not None and not f.is_file():
            raise UserError(f"{path}: {name} file {f} does not exist")
    if creds.key is not None:
        check_private(creds.key, "private key", strict)
    return creds


def write_credentials(path: str | os.PathLike[str], creds: Credentials) -> Path:
    """Write ``creds`` as a credentials file (mode 0600, paths relative to its directory)."""
    p = Path(path)
    doc = creds.to_json(relative_to=p.resolve().parent)
    return write_private(p, json.dumps(doc, indent=2) + "\n")


def client_settings(creds: Credentials) -> dict[str, Any]:
    """The Zenoh configuration entries (``key -> value``) that present ``creds``.

    * password: ``transport/auth/usrpwd/{user,password}``;
    * CA: ``transport/link/tls/root_ca_certificate`` (verifies the router on ``tls/``
      endpoints);
    * client certificate: ``transport/link/tls/{connect_certificate,connect_private_key}`` and
      ``enable_mtls: true`` -- verified here: without ``enable_mtls`` the client sends no
      certificate and an mTLS router refuses it.
    """
    out: dict[str, Any] = {}
    if creds.user is not None:
        out["transport/auth/usrpwd/user"] = creds.user
        out["transport/auth/usrpwd/password"] = creds.password
    if creds.ca is not None:
        out["transport/link/tls/root_ca_certificate"] = str(creds.ca)
    if creds.cert is not None and creds.key is not None:
        out["transport/link/tls/connect_certificate"] = str(creds.cert)
        out["transport/link/tls/connect_private_key"] = str(creds.key)
        out["transport/link/tls/enable_mtls"] = True
    return out


def apply_credentials(cfg: zenoh.Config, creds: Credentials) -> zenoh.Config:
    """Add ``creds`` to a client (or peer) configuration in place and return it.

    Endpoints are not changed: with TLS material, connect to ``tls/host:port`` where ``host``
    matches the router certificate's SAN (``localhost`` or ``127.0.0.1`` for test certificates).

    Raises
    ------
    UserError
        When Zenoh rejects a value.
    """
    for key, value in client_settings(creds).items():
        try:
            cfg.insert_json5(key, json.dumps(value))
        except Exception as exc:
            raise UserError(f"cannot apply credentials ({key}): {' '.join(str(exc).split())[:300]}") from None
    return cfg


# ---------------------------------------------------------------------- password dictionary
def make_password(nbytes: int = 18) -> str:
    """A random password: ``nbytes`` from ``secrets``, URL-safe base64 (no ``:``, no newline)."""
    return secrets.token_urlsafe(nbytes)


def password_dictionary(users: Mapping[str, str]) -> str:
    """The router's ``dictionary_file`` text: one ``user:password`` line per user, sorted.

    Raises
    ------
    UserError
        A user name that is not a valid id, or a password with a newline or that is empty.
    """
    lines = []
    for user in sorted(users):
        _check_id(user, "user name")
        pw = users[user]
        if not isinstance(pw, str) or not pw or any(c in pw for c in "\r\n"):
            raise UserError(f"bad password for {user!r}: must be one non-empty line")
        lines.append(f"{user}:{pw}\n")
    return "".join(lines)


def write_password_dictionary(path: str | os.PathLike[str], users: Mapping[str, str]) -> Path:
    """Write :func:`password_dictionary` to ``path`` with mode 0600."""
    return write_private(path, password_dictionary(users))


# ---------------------------------------------------------------------- access control
def _rule(rid: str, messages: Sequence[str], flow: str, key_exprs: Sequence[str]) -> dict[str, Any]:
    return {
        "id": rid,
        "messages": list(messages),
        "flows": [flow],
        "permission": "allow",
        "key_exprs": list(key_exprs),
    }


def fuser_identity(group: str) -> str:
    """The identity (user name, certificate CN, credentials file name) of the regional fuser of
    ``group`` in a secure fusion tree: ``fuser-<group>``."""
    return f"fuser-{group}"


READ_IN = ("declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query")
READ_OUT = ("put", "delete", "reply", "liveliness_token")


def acl_config(
    fleet: str,
    robots: list[str],
    fusion_user: str = DEFAULT_FUSION_USER,
    *,
    observers: Sequence[str] = (),
    identity: Identity = "username",
    fusers: Sequence[str] = (),
) -> dict[str, Any]:
    """The router's ``access_control`` section for one fleet (default deny).

    Parameters
    ----------
    fleet : the fleet name (``wiremap/<fleet>/...``).
    robots : robot ids; robot ``ID`` authenticates as user (or certificate CN) ``ID``.
    fusion_user : the fusion service's identity, the only one allowed to write ``fused/**``.
    observers : identities that may read the whole fleet but write nothing.
    identity : how a client is matched to an id: ``"username"`` (usrpwd), ``"cert"``
        (mTLS certificate common name) or ``"both"`` (user name and CN must both equal the id).
    fusers : the group names of a fusion tree's regional fusers (``wiremap fuse --group
        NAME``); the fuser of group ``NAME`` authenticates as :func:`fuser_identity` (``NAME``),
        i.e. ``fuser-NAME``, and may write only its group's keys; the root is ``fusion_user``.

    Returns
    -------
    dict
        ``{"enabled": True, "default_permission": "deny", "rules": [...], "subjects": [...],
        "policies": [...]}``, ready for ``access_control`` in a router configuration. The table
        in the module docstring says what each role may do. Flows are explicit: ``ingress``
        rules say what a client may send to the router, ``egress`` rules what the router
        forwards to it.

    Raises
    ------
    UserError
        A bad fleet name or id, a duplicate, or an id used for two roles.
    """
    _check_id(fleet, "fleet name")
    _check_id(fusion_user, "fusion user")
    groups = [_check_id(g, "fuser group") for g in fusers]
    for g in groups:
        if g == "root":
            raise UserError("fuser group 'root' is reserved (the root's token is fusers/root)")
    ids = [_check_id(r, "robot id") for r in robots] + [_check_id(o, "observer") for o in observers]
    ids += [_check_id(fuser_identity(g), "fuser identity") for g in groups]
    seen: set[str] = {fusion_user}
    for i in ids:
        if i in seen:
            raise UserError(
                f"identity {i!r} is used twice (robots, observers and the fusion user must differ)"
            )
        seen.add(i)
    if identity not in ("username", "cert", "both"):
        raise UserError(f"bad identity kind {identity!r}: use username, cert or both")

    def subject(sid: str, name: str) -> dict[str, Any]:
        s: dict[str, Any] = {"id": sid}
        if identity in ("username", "both"):
            s["usernames"] = [name]
        if identity in ("cert", "both"):
            s["cert_common_names"] = [name]
        return s

    p = f"wiremap/{fleet}"
    fleet_read = [f"{p}/robots/**", f"{p}/alive/**", f"{p}/fused/**"]
    rules = [
        _rule("any-read-fused-in", ["declare_subscriber", "query"], "ingress", [f"{p}/fused/**"]),
        _rule("any-read-fused-out", ["put", "delete", "reply"], "egress", [f"{p}/fused/**"]),
        _rule("any-alive-in", ["declare_liveliness_subscriber", "liveliness_query"], "ingress",
              [f"{p}/alive/**"]),
        _rule("any-alive-out", ["liveliness_token", "reply"], "egress", [f"{p}/alive/**"]),
        # reading the fleet: everything but admin/** (an observer may not ask the fusion
        # service to forget a robot)
        _rule("fleet-read-in", READ_IN, "ingress", fleet_read),
        _rule("fleet-read-out", READ_OUT, "egress", fleet_read),
        _rule("fusion-write", ["put", "delete", "declare_queryable", "reply"], "ingress", [f"{p}/fused/**"]),
        _rule("fusion-answer", ["query"], "egress", [f"{p}/fused/**"]),
        # admin/** (``wiremap fleet forget``): asked and answered by the fusion identity only
        _rule("admin-in", ["query", "declare_queryable", "reply"], "ingress", [f"{p}/admin/**"]),
        _rule("admin-out", ["query", "reply"], "egress", [f"{p}/admin/**"]),
    ]
    tree_read = [f"{p}/groups/**", f"{p}/fusers/**"]
    if groups:
        # the fusion tree: everyone who reads the fleet reads the partials and the fusers'
        # tokens; the root (the fusion identity) declares the root tokens only
        rules += [
            _rule("tree-read-in", READ_IN, "ingress", tree_read),
            _rule("tree-read-out", READ_OUT, "egress", tree_read),
            _rule("root-token", ["liveliness_token"], "ingress",
                  [f"{p}/fusers/root", f"{p}/fusers/root/*"]),
        ]
    tree_rules = ["tree-read-in", "tree-read-out"] if groups else []
    subjects: list[dict[str, Any]] = [subject("fusion", fusion_user)]
    if identity != "both":
        subjects.insert(0, {"id": "any"})
    # "any" authenticated client: with identity "both", only the clients whose user name and
    # certificate CN are one known identity (a subject with neither would also match r2's
    # certificate logged in with r1's password, which must be able to do nothing at all)
    everyone = ["fusion", *(f"observer-{o}" for o in observers), *(f"robot-{r}" for r in robots),
                *(fuser_identity(g) for g in groups)]
    policies: list[dict[str, Any]] = [
        {"id": "any", "rules": ["any-read-fused-in", "any-read-fused-out", "any-alive-in", "any-alive-out"],
         "subjects": everyone if identity == "both" else ["any"]},
        {"id": "fusion",
         "rules": ["fleet-read-in", "fleet-read-out", "fusion-write", "fusion-answer", "admin-in",
                   "admin-out", *tree_rules, *(["root-token"] if groups else [])],
         "subjects": ["fusion"]},
    ]
    if observers:
        for o in observers:
            subjects.append(subject(f"observer-{o}", o))
        policies.append({"id": "observers", "rules": ["fleet-read-in", "fleet-read-out", *tree_rules],
                         "subjects": [f"observer-{o}" for o in observers]})
    for g in groups:
        # a regional fuser: reads the fleet and the tree, writes (puts, its queryables' replies)
        # only under groups/NAME/** and declares only the token fusers/NAME; it receives the
        # queries for its own keys only
        fid = fuser_identity(g)
        rules.append(_rule(f"{fid}-write", ["put", "delete", "declare_queryable", "reply"], "ingress",
                           [f"{p}/groups/{g}/**"]))
        rules.append(_rule(f"{fid}-answer", ["query"], "egress", [f"{p}/groups/{g}/**"]))
        rules.append(_rule(f"{fid}-token", ["liveliness_token"], "ingress", [f"{p}/fusers/{g}"]))
        subjects.append(subject(fid, fid))
        policies.append({"id": fid,
                         "rules": ["fleet-read-in", "fleet-read-out", *tree_rules, f"{fid}-write",
                                   f"{fid}-answer", f"{fid}-token"],
                         "subjects": [fid]})
    for r in robots:
        rules.append(_rule(f"robot-{r}-write", ["put", "delete"], "ingress", [f"{p}/robots/{r}/**"]))
        rules.append(_rule(f"robot-{r}-alive", ["liveliness_token"], "ingress", [f"{p}/alive/{r}"]))
        subjects.append(subject(f"robot-{r}", r))
        policies.append({"id": f"robot-{r}", "rules": [f"robot-{r}-write", f"robot-{r}-alive"],
                         "subjects": [f"robot-{r}"]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


# ---------------------------------------------------------------------- router configuration
@dataclass(frozen=True)
class ServerTls:
    """A router's TLS files: the fleet CA, its certificate (SAN = the host clients dial) and key."""

    ca: Path
    cert: Path
    key: Path


def router_config(
    listen: Sequence[str],
    *,
    dictionary_file: str | os.PathLike[str] | None = None,
    tls: ServerTls | None = None,
    mtls: bool = True,
    acl: Mapping[str, Any] | None = None,
    connect: Sequence[str] = (),
) -> dict[str, Any]:
    """A router configuration (a nested dict, as in a JSON5 file).

    Parameters
    ----------
    listen : endpoints, e.g. ``["tls/localhost:7447"]`` or ``["tcp/127.0.0.1:7447"]``.
    dictionary_file : enables user/password authentication with this ``user:password`` file.
    tls : the router's TLS files (needed for ``tls/`` endpoints).
    mtls : with ``tls``, require a client certificate signed by ``tls.ca``.
    acl : an ``access_control`` section (:func:`acl_config`).
    connect : other routers to connect to.

    Multicast scouting is off (as in every wiremap configuration).
    """
    cfg: dict[str, Any] = {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "scouting": {"multicast": {"enabled": False}},
    }
    if connect:
        cfg["connect"] = {"endpoints": list(connect)}
    transport: dict[str, Any] = {}
    if dictionary_file is not None:
        transport["auth"] = {"usrpwd": {"dictionary_file": str(dictionary_file)}}
    if tls is not None:
        transport["link"] = {
            "tls": {
                "root_ca_certificate": str(tls.ca),
                "listen_certificate": str(tls.cert),
                "listen_private_key": str(tls.key),
                "enable_mtls": bool(mtls),
            }
        }
    if transport:
        cfg["transport"] = transport
    if acl is not None:
        cfg["access_control"] = dict(acl)
    return cfg


def to_zenoh_config(doc: Mapping[str, Any]) -> zenoh.Config:
    """A ``zenoh.Config`` from a nested dict such as :func:`router_config` returns.

    Raises
    ------
    UserError
        When Zenoh rejects the document.
    """
    import zenoh

    try:
        return zenoh.Config.from_json5(json.dumps(doc))
    except Exception as exc:
        raise UserError(f"invalid Zenoh configuration: {' '.join(str(exc).split())[:300]}") from None


# ---------------------------------------------------------------------- certificates
def _openssl(args: Sequence[str], stdin: bytes | None = None) -> bytes:
    exe = shutil.which("openssl")
    if exe is None:
        raise UserError("the 'openssl' command is needed to generate certificates and is not on PATH")
    proc = subprocess.run([exe, *args], input=stdin, capture_output=True, check=False)
    if proc.returncode != 0:
        raise UserError(f"openssl {args[0]} failed: {proc.stderr.decode(errors='replace').strip()}")
    return proc.stdout


def _new_key(path: Path) -> Path:
    # EC P-256 (fast to generate, accepted by rustls); written 0600 by us, never by openssl
    pem = _openssl(["genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256"])
    return write_private(path, pem)


def generate_ca(directory: str | os.PathLike[str], name: str = "ca", days: int = 30) -> tuple[Path, Path]:
    """A self-signed CA: ``<name>.pem`` and ``<name>.key`` (0600) in ``directory``."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    key = _new_key(d / f"{name}.key")
    pem = d / f"{name}.pem"
    _openssl([
        "req", "-x509", "-new", "-key", str(key), "-days", str(int(days)), "-subj", "/CN=wiremap fleet CA",
        "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        "-out", str(pem),
    ])
    return pem, key


def generate_cert(
    directory: str | os.PathLike[str],
    name: str,
    ca: tuple[Path, Path],
    *,
    common_name: str | None = None,
    server_names: Sequence[str] = (),
    days: int = 30,
) -> tuple[Path, Path]:
    """A certificate signed by ``ca = (ca_pem, ca_key)``: ``<name>.pem`` and ``<name>.key`` (0600).

    With ``server_names`` it is a server certificate (``extendedKeyUsage = serverAuth``, one SAN
    per name: ``IP:`` for addresses, ``DNS:`` otherwise); without, a client certificate
    (``clientAuth``). ``common_name`` defaults to ``name``: for clients it is the identity the
    ACL's ``cert_common_names`` match.
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    cn = common_name or name
    if not re.match(r"^[A-Za-z0-9][A-Za-z0-9_. -]{0,62}$", cn):
        raise UserError(f"bad certificate common name {cn!r}")
    key = _new_key(d / f"{name}.key")
    pem = d / f"{name}.pem"
    ext = ["basicConstraints=CA:FALSE", "keyUsage=critical,digitalSignature"]
    if server_names:
        sans = []
        for n in server_names:
            try:
                socket.inet_pton(socket.AF_INET6 if ":" in n else socket.AF_INET, n)
                sans.append(f"IP:{n}")
            except OSError:
                sans.append(f"DNS:{n}")
        ext += ["extendedKeyUsage=serverAuth", "subjectAltName=" + ",".join(sans)]
    else:
        ext += ["extendedKeyUsage=clientAuth"]
    with tempfile.TemporaryDirectory(prefix="wiremap-cert-") as tmp:
        csr = Path(tmp) / "req.csr"
        extfile = Path(tmp) / "ext.cnf"
        extfile.write_text("\n".join(ext) + "\n")
        _openssl(["req", "-new", "-key", str(key), "-subj", f"/CN={cn}", "-out", str(csr)])
        _openssl([
            "x509", "-req", "-in", str(csr), "-CA", str(ca[0]), "-CAkey", str(ca[1]),
            "-set_serial", str(secrets.randbits(63) + 1), "-days", str(int(days)),
            "-extfile", str(extfile), "-out", str(pem),
        ])
    return pem, key


@dataclass(frozen=True)
class CertSet:
    """Files written by :func:`generate_test_certs`; ``clients[id] = (pem, key)``."""

    ca: Path
    ca_key: Path
    server: ServerTls
    clients: dict[str, tuple[Path, Path]]

    def client_credentials(
        self, name: str, user: str | None = None, password: str | None = None
    ) -> Credentials:
        pem, key = self.clients[name]
        return Credentials(user=user, password=password, ca=self.ca, cert=pem, key=key)


def generate_test_certs(
    directory: str | os.PathLike[str],
    clients: Iterable[str],
    hosts: Sequence[str] = ("localhost", "127.0.0.1"),
    days: int = 30,
) -> CertSet:
    """A CA, a server certificate for ``hosts`` and one client certificate per id (CN = id).

    For tests and demos: the CA key is kept next to the CA (``ca.key``, 0600) so that more
    robots can be added with :func:`generate_cert`. About 0.1 s per certificate here.
    """
    d = Path(directory)
    ca = generate_ca(d, "ca", days)
    spem, skey = generate_cert(d, "server", ca, common_name=hosts[0] if hosts else "router",
                               server_names=hosts, days=days)
    out: dict[str, tuple[Path, Path]] = {}
    for c in clients:
        _check_id(c, "client id")
        if c in ("ca", "server"):
            raise UserError(f"client id {c!r} clashes with a certificate file name")
        out[c] = generate_cert(d, c, ca, common_name=c, days=days)
    return CertSet(ca=ca[0], ca_key=ca[1], server=ServerTls(ca=ca[0], cert=spem, key=skey), clients=out)


# ---------------------------------------------------------------------- a whole fleet
@dataclass(frozen=True)
class SecureFleet:
    """Everything :func:`make_secure_fleet` wrote.

    Attributes
    ----------
    directory : the root (``certs/``, ``credentials/<id>.json``, ``passwords.txt``,
        ``router.json5``).
    router : the router configuration (also in ``router_file``).
    credentials : ``id -> credentials file`` for every robot, the fusion user and observers.
    endpoint : what clients connect to.
    """

    directory: Path
    router: dict[str, Any]
    router_file: Path
    credentials: dict[str, Path]
    endpoint: str


def make_secure_fleet(
    directory: str | os.PathLike[str],
    fleet: str,
    robots: Sequence[str],
    *,
    fusion_user: str = DEFAULT_FUSION_USER,
    observers: Sequence[str] = (DEFAULT_OBSERVER,),
    listen: str = f"tls/localhost:{DEFAULT_SECURE_PORT}",
    usrpwd: bool = True,
    mtls: bool = True,
    fusers: Sequence[str] = (),
) -> SecureFleet:
    """Write credentials for a fleet: certificates, passwords, one credentials file per
    identity and the router configuration with the fleet's ACL.

    Parameters
    ----------
    directory : created if needed; existing files in it are replaced.
    fleet, robots, fusion_user, observers : as in :func:`acl_config`.
    listen : the router endpoint; with ``mtls`` it must be a ``tls/`` endpoint whose host is
        ``localhost`` or ``127.0.0.1`` (the SANs of the generated server certificate).
    usrpwd : user/password authentication (random passwords, :func:`make_password`).
    mtls : mutual TLS with generated certificates (CN = id).
    fusers : a fusion tree's group names: one identity and credentials file per regional
        fuser, ``fuser-NAME`` (:func:`fuser_identity`); the root uses ``fusion_user``.

    With both, the ACL identifies a client by user name *and* certificate CN
    (``identity="both"``; a client whose two do not name one identity may do nothing); with
    one, by that one. At least one must be on. The CA's private key is deleted once the
    certificates are issued: it is never part of the written folder.
    """
    if not (usrpwd or mtls):
        raise UserError("a secure fleet needs user/password authentication, mutual TLS or both")
    if mtls and not listen.startswith("tls/"):
        raise UserError(f"mutual TLS needs a tls/ endpoint, not {listen!r}")
    identity: Identity = "both" if (usrpwd and mtls) else ("username" if usrpwd else "cert")
    acl = acl_config(fleet, list(robots), fusion_user, observers=observers, identity=identity,
                     fusers=fusers)
    d = Path(directory).resolve()
    ids = [fusion_user, *observers, *robots, *(fuser_identity(g) for g in fusers)]
    certs = generate_test_certs(d / "certs", ids) if mtls else None
    if certs is not None:
        # every certificate of the fleet is issued: the CA's private key would only let whoever
        # reads this folder (a run's outputs) mint identities, so it is not kept (a new robot
        # means new fleet credentials)
        certs.ca_key.unlink()
    passwords = {i: make_password() for i in ids} if usrpwd else {}
    dictionary = write_password_dictionary(d / "passwords.txt", passwords) if usrpwd else None
    creds: dict[str, Path] = {}
    for i in ids:
        c = Credentials(
            user=i if usrpwd else None,
            password=passwords.get(i),
            ca=certs.ca if certs else None,
            cert=certs.clients[i][0] if certs else None,
            key=certs.clients[i][1] if certs else None,
        )
        creds[i] = write_credentials(d / "credentials" / f"{i}.json", c)
    router = router_config([listen], dictionary_file=dictionary, tls=certs.server if certs else None, acl=acl)
    header = (
        f"// wiremap secure router for fleet {fleet!r}, written by agents.fleet.secure.make_secure_fleet\n"
    )
    router_file = write_private(d / "router.json5", header + json.dumps(router, indent=2) + "\n")
    return SecureFleet(directory=d, router=router, router_file=router_file, credentials=creds,
                       endpoint=listen)


# ---------------------------------------------------------------------- diagnosis
def endpoint_address(endpoint: str) -> tuple[str, int] | None:
    """``(host, port)`` of a ``tcp/``, ``tls/`` or ``quic/`` endpoint (``[v6]`` allowed), else None."""
    m = re.match(r"^(?:tcp|tls|quic)/(\[[^\]]+\]|[^:/\[\]]+):(\d+)(?:[?#].*)?$", endpoint)
    if not m:
        return None
    return m.group(1).strip("[]"), int(m.group(2))


def endpoint_reachable(endpoint: str, timeout: float = 0.5) -> bool:
    """Whether something accepts TCP connections at ``endpoint``'s address.

    Zenoh reports a refused authentication (wrong password, no or a foreign certificate) with
    the same "Unable to connect" error as an absent router; when this returns True after such
    an error, the router is there and refused us: the caller should stop waiting and say so.
    """
    addr = endpoint_address(endpoint)
    if addr is None:
        return False
    try:
        with socket.create_connection(addr, timeout=timeout):
            return True
    except OSError:
        return False


# ---------------------------------------------------------------------- command line
def main(argv: Sequence[str] | None = None) -> int:
    """``python -m agents.fleet.secure init DIR --fleet F --robots r1,r2 [...]`` (see :func:`make_secure_fleet`)."""  # noqa: E501
    ap = argparse.ArgumentParser(prog="python -m agents.fleet.secure",
                                 description="wiremap fleet credentials")
    sub = ap.add_subparsers(dest="cmd", required=True)
    init = sub.add_parser("init", help="write certificates, passwords, credentials files and a router config")
    init.add_argument("directory")
    init.add_argument("--fleet", default="default")
    init.add_argument("--robots", required=True, help="comma-separated robot ids")
    init.add_argument("--fusion-user", default=DEFAULT_FUSION_USER)
    init.add_argument("--fusers", default="",
                      help="comma-separated group names of a fusion tree's regional fusers "
                           "(identities fuser-NAME)")
    init.add_argument("--observers", default=DEFAULT_OBSERVER,
                      help="comma-separated read-only ids ('' for none)")
    init.add_argument("--listen", default=f"tls/localhost:{DEFAULT_SECURE_PORT}")
    init.add_argument("--no-usrpwd", action="store_true", help="mutual TLS only")
    init.add_argument("--no-mtls", action="store_true",
                      help="user/password only (plain TCP: use a tcp/ endpoint)")
    init.add_argument("--force", action="store_true", help="replace existing files")
    args = ap.parse_args(argv)
    try:
        d = Path(args.directory)
        if not args.force and any(
            (d / n).exists() for n in ("certs", "credentials", "passwords.txt", "router.json5")
        ):
            raise UserError(f"{d} already holds credentials (use --force to replace them)")
        robots = [r for r in args.robots.split(",") if r]
        observers = [o for o in args.observers.split(",") if o]
        fl = make_secure_fleet(
            d, args.fleet, robots, fusion_user=args.fusion_user, observers=observers,
            listen=args.listen, usrpwd=not args.no_usrpwd, mtls=not args.no_mtls,
            fusers=[g for g in args.fusers.split(",") if g],
        )
    except UserError as exc:
        print(f"wiremap: {exc}", file=sys.stderr)
        return 2
    print(f"router:      wiremap router --config {fl.router_file}")
    for i, p in fl.credentials.items():
        print(f"{i:12} --connect {fl.endpoint} --credentials {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
