"""The secure lab mode: one lab file → the Zenoh configurations of a training lab (``dhg lab-config``).

A lab runs one server (``dhg-serve``), haptic stations, instructors and model workers on one
network. In the open mode any peer can put a force on any session's key, reset any session and
answer the model's queries. The lab file names every identity, and this module writes, for each,
a Zenoh configuration that

* encrypts every link with TLS (the server's certificate signed by the lab's CA; clients verify it),
* authenticates every client by user name and password (the server holds the dictionary),
* and gives the server an access-control list (deny by default) in which

  - a **station** may publish only its own poses, query only its own control, info, metrics,
    X-rays and bone (and the server's health, volume and about), and hear (and recover) only its
    own outputs. Its sessions are named ``<station>`` or ``<station>-<anything>``, so no station
    may be named another's name plus ``-...``;
  - an **instructor** may read every session (subscribe to every output and recover the recorded
    streams, query every session's read-only keys, info, metrics, X-rays and bone, and the
    server's health, volume and about) and change none: no pose, no control, no model query;
  - a **model worker** may join the engine's worker pool under its own name (the liveliness
    token ``<prefix>/model/workers/<name>`` and the queryable below it), serve the shared
    ``<prefix>/model/predict``, and nothing else;
  - the **server** identity (its own model, X-ray, bone and about services, which connect to its
    engine over loopback) does the same as worker ``dhg-server`` and serves X-rays, the bone, the
    volume and ``about``;
  - nobody but the engine publishes a force, guidance, state or ticks: no client rule allows it.

The lab file (TOML)::

    [server]
    endpoint = "tls/dhg-server.lab:7447"      # where clients connect
    listen = "tls/0.0.0.0:7447"               # optional: where the server listens (default: endpoint)
    prefix = "dhg"                            # optional
    ca_certificate = "certs/ca.pem"           # the lab's CA (relative to the lab file)
    certificate = "certs/server.pem"          # the server's certificate and key, signed by the CA
    private_key = "certs/server-key.pem"
    password = "..."                          # the server identity's own password
    sessions_per_station = 2                  # optional: what dhg-serve --lab lets one station hold

    [[station]]
    name = "station-1"
    password = "..."

    [[instructor]]
    name = "instructor"
    password = "..."

    [[model_worker]]
    name = "model-1"
    password = "..."

``dhg lab-config --lab lab.toml --out DIR`` writes ``DIR/server.json5`` (for ``dhg-serve
--zenoh-config``), ``DIR/users.txt`` (the password dictionary it names) and ``DIR/<name>.json5``
for every other identity (for ``--zenoh-config`` of ``dhg trainee``, ``record``, ``study --live``
and model workers). ``--make-certs`` first creates a lab CA and a server certificate with
``openssl`` where the files do not exist. ``docs/deployment.md`` is the how-to.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import tempfile
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dhg.core.errors import InvalidInputError
from dhg.core.protocol import check_session_id, server_key, session_key, shared_predict_key, worker_key

__all__ = ["Identity", "Lab", "acl", "load_lab", "make_certs", "write_lab"]

ROLES = ("station", "instructor", "model_worker")
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,47}")
SERVER_IDENTITY = "dhg-server"
"""The user name of the server's own services (model, X-rays) when they connect to its engine."""
_RECOVERABLE = ("guidance", "state", "ticks")
"""The streams a recorder recovers (zenoh-ext advanced publishers): their heartbeats, liveliness
tokens and cache queries live under ``<stream>/@adv/...``, a verbatim chunk ``**`` never matches."""
_HEARD = (
    "force",
    "view/force",
    "view/pose",
    *_RECOVERABLE,
    *(f"{leaf}/**" for leaf in _RECOVERABLE),
    *(f"{leaf}/@adv/**" for leaf in _RECOVERABLE),
)
"""A station's own streams it may subscribe to."""
_READ = ("info", "metrics", "xray/*", "bone")
"""A session's keys that answer queries without changing it."""


@dataclass(frozen=True)
class Identity:
    """One client of the lab: ``role`` (station, instructor, model_worker), a user name and password."""

    role: str
    name: str
    password: str


@dataclass
class Lab:
    """A lab file, read (paths absolute)."""

    endpoint: str
    listen: str
    prefix: str
    ca_certificate: Path
    certificate: Path
    private_key: Path
    server_password: str
    sessions_per_station: int = 2
    """Most sessions one station may hold at once (``dhg-serve --lab`` enforces it)."""
    identities: list[Identity] = field(default_factory=list)

    def of(self, role: str) -> list[Identity]:
        return [i for i in self.identities if i.role == role]


def _need(table: dict[str, Any], key: str, where: str) -> Any:
    if key not in table:
        raise InvalidInputError(f"{where}: '{key}' is missing")
    return table[key]


def load_lab(path: str | os.PathLike[str]) -> Lab:
    """Reads and checks a lab file (see the module docs)."""
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise InvalidInputError(f"{p}: not a readable TOML lab file ({exc})") from None
    server = _need(data, "server", str(p))
    base = p.parent

    def rel(key: str) -> Path:
        return (base / str(_need(server, key, f"{p} [server]"))).resolve()

    endpoint = str(_need(server, "endpoint", f"{p} [server]"))
    if not endpoint.startswith("tls/"):
        raise InvalidInputError(f"{p} [server]: the endpoint must be a tls/ endpoint, got {endpoint!r}")
    prefix = str(server.get("prefix", "dhg"))
    for seg in prefix.split("/"):
        check_session_id(seg)
    lab = Lab(
        endpoint=endpoint,
        listen=str(server.get("listen", endpoint)),
        prefix=prefix,
        ca_certificate=rel("ca_certificate"),
        certificate=rel("certificate"),
        private_key=rel("private_key"),
        server_password=str(_need(server, "password", f"{p} [server]")),
        sessions_per_station=int(server.get("sessions_per_station", 2)),
    )
    if lab.sessions_per_station < 1:
        raise InvalidInputError(f"{p} [server]: sessions_per_station must be at least 1")
    seen = {SERVER_IDENTITY}
    for role in ROLES:
        for k, entry in enumerate(data.get(role, [])):
            where = f"{p} [[{role}]] #{k + 1}"
            name, password = str(_need(entry, "name", where)), str(_need(entry, "password", where))
            if not _NAME.fullmatch(name):
                raise InvalidInputError(
                    f"{where}: name {name!r} must be 1-48 of A-Z a-z 0-9 _ . -, the first alphanumeric"
                )
            if name in seen:
                raise InvalidInputError(f"{where}: the name {name!r} is used twice")
            if len(password) < 8 or ":" in password or "\n" in password:
                raise InvalidInputError(f"{where}: the password must have at least 8 characters, without ':'")
            seen.add(name)
            lab.identities.append(Identity(role, name, password))
    if not lab.of("station"):
        raise InvalidInputError(f"{p}: a lab needs at least one [[station]]")
    # A station drives its sessions <name> and <name>-*: "room" would drive "room-2"'s.
    stations = sorted(s.name for s in lab.of("station"))
    for a in stations:
        for b in stations:
            if b.startswith(a + "-"):
                raise InvalidInputError(
                    f"{p}: station {a!r} would drive station {b!r}'s sessions ({a}-* names {b}'s): rename one"
                )
    return lab


def _rule(rid: str, messages: list[str], flows: list[str], keys: list[str]) -> dict[str, Any]:
    return {"id": rid, "messages": messages, "flows": flows, "permission": "allow", "key_exprs": keys}


def _recovery_keys(sessions: list[str]) -> list[str]:
    """What a recorder of ``sessions`` (session key roots) queries and is answered on to recover
    the recorded streams: below each stream, and its advanced publisher's ``@adv/...`` keys."""
    return [f"{s}/{leaf}/{tail}" for s in sessions for leaf in _RECOVERABLE for tail in ("**", "@adv/**")]


def _station_rules(p: str, n: str, server: list[str]) -> list[dict[str, Any]]:
    """Station ``n``'s rules under prefix ``p``: it drives and reads only its own sessions (``n``
    and ``n-*``), and asks the server's keys ``server`` (health, volume, about)."""
    own = [session_key(p, n), session_key(p, f"{n}-$*")]
    rid = f"station:{n}"  # rule ids are unique across roles (a station may be named "instructor")
    recover = _recovery_keys(own)
    return [
        _rule(f"{rid}:pose", ["put"], ["ingress"], [f"{s}/pose" for s in own]),
        _rule(
            f"{rid}:ask",
            ["query"],
            ["ingress"],
            server + [f"{s}/{leaf}" for s in own for leaf in ("control", *_READ)],
        ),
        _rule(f"{rid}:replies", ["reply"], ["egress"], server + [f"{s}/**" for s in own] + recover),
        _rule(
            f"{rid}:hear",
            ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
            ["ingress"],
            [f"{s}/{leaf}" for s in own for leaf in _HEARD],
        ),
        _rule(
            f"{rid}:outputs",
            ["put", "liveliness_token"],
            ["egress"],
            [f"{s}/{leaf}" for s in own for leaf in _HEARD],
        ),
        _rule(f"{rid}:recover", ["query"], ["ingress"], recover),
    ]


def _instructor_rules(p: str, server: list[str]) -> list[dict[str, Any]]:
    """The instructors' rules under prefix ``p``: they hear every session's streams and ask its
    read-only keys (``info``, ``metrics``, X-rays, bone) and the server's ``server``, and change
    nothing: no pose, no ``control``, no model query."""
    every = session_key(p, "*")
    heard = [f"{every}/{leaf}" for leaf in _HEARD]
    asked = server + [f"{every}/{leaf}" for leaf in _READ]
    recover = _recovery_keys([every])
    return [
        _rule(
            "instructors:read",
            ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
            ["ingress"],
            heard,
        ),
        _rule("instructors:ask", ["query"], ["ingress"], asked + recover),
        _rule("instructors:hear", ["put", "liveliness_token"], ["egress"], heard),
        _rule("instructors:replies", ["reply"], ["egress"], asked + recover),
    ]


def _worker_rules(p: str, n: str, served: list[str]) -> list[dict[str, Any]]:
    """Model worker ``n``'s rules under prefix ``p`` (the server's own identity also serves the
    X-rays, the bone, and the server's Python keys ``served``: the volume and about). A worker
    asks the server's ``about`` to check that the engine's corridor is its model's
    (:class:`dhg.live.services.CorridorCheck`)."""
    own = worker_key(p, n)
    extra = [session_key(p, "*", "xray/*"), session_key(p, "*", "bone"), *served] if n == SERVER_IDENTITY else []
    rules = [
        _rule(
            f"worker:{n}:serve",
            ["declare_queryable", "reply"],
            ["ingress"],
            [shared_predict_key(p), f"{own}/predict"] + extra,
        ),
        _rule(f"worker:{n}:join", ["liveliness_token"], ["ingress"], [own]),
        _rule(f"worker:{n}:queries", ["query"], ["egress"], [shared_predict_key(p), f"{own}/predict"] + extra),
    ]
    if n != SERVER_IDENTITY:
        about = [server_key(p, "about")]
        rules += [
            _rule(f"worker:{n}:ask", ["query"], ["ingress"], about),
            _rule(f"worker:{n}:answers", ["reply"], ["egress"], about),
        ]
    return rules


def acl(lab: Lab) -> dict[str, Any]:
    """The server's access-control list (Zenoh ``access_control``) for the lab's identities."""
    p = lab.prefix
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []

    def grant(who: str, names: list[str], *granted: dict[str, Any]) -> None:
        subjects.append({"id": who, "usernames": names})
        rules.extend(granted)
        policies.append({"rules": [r["id"] for r in granted], "subjects": [who]})

    health, served = server_key(p, "health"), [server_key(p, "volume"), server_key(p, "about")]
    for st in lab.of("station"):
        grant(f"station:{st.name}", [st.name], *_station_rules(p, st.name, [health, *served]))
    instructors = [i.name for i in lab.of("instructor")]
    if instructors:
        grant("instructors", instructors, *_instructor_rules(p, [health, *served]))
    # A model worker joins the engine's pool under its own name only (its token and its
    # queryable), and may serve the shared key the engine queries while the pool is empty.
    for n in [i.name for i in lab.of("model_worker")] + [SERVER_IDENTITY]:
        grant(f"worker:{n}", [n], *_worker_rules(p, n, served))
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def _tls(lab: Lab, server: bool) -> dict[str, Any]:
    tls: dict[str, Any] = {"root_ca_certificate": str(lab.ca_certificate), "verify_name_on_connect": True}
    if server:
        tls |= {"listen_certificate": str(lab.certificate), "listen_private_key": str(lab.private_key)}
    return tls


def _base(mode: str, lab: Lab, user: str, password: str, server: bool) -> dict[str, Any]:
    return {
        "mode": mode,
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "link": {"tls": _tls(lab, server)},
            "auth": {"usrpwd": {"user": user, "password": password}},
        },
    }


def lab_configs(lab: Lab, users_file: Path) -> dict[str, dict[str, Any]]:
    """``{"server": ..., "<name>": ...}``: the Zenoh configuration of each lab member."""
    server = _base("router", lab, SERVER_IDENTITY, lab.server_password, server=True)
    server["listen"] = {"endpoints": [lab.listen]}
    server["transport"]["auth"]["usrpwd"]["dictionary_file"] = str(users_file)
    server["access_control"] = acl(lab)
    out = {"server": server}
    for ident in lab.identities:
        conf = _base("client", lab, ident.name, ident.password, server=False)
        conf["connect"] = {"endpoints": [lab.endpoint]}
        out[ident.name] = conf
    return out


def write_lab(lab_path: str | os.PathLike[str], out_dir: str | os.PathLike[str], certs: bool = False) -> list[Path]:
    """Writes every configuration of the lab file into ``out_dir`` (see the module docs); with
    ``certs``, first creates the lab CA and the server certificate where they do not exist.
    Returns the files written. Files with passwords are readable by their owner only."""
    lab = load_lab(lab_path)
    if certs:
        make_certs(lab)
    for f in (lab.ca_certificate, lab.certificate, lab.private_key):
        if not f.is_file():
            raise InvalidInputError(
                f"{f}: no such file (run with --make-certs to create a lab CA and server certificate)"
            )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    users = out / "users.txt"
    lines = [f"{SERVER_IDENTITY}:{lab.server_password}"] + [f"{i.name}:{i.password}" for i in lab.identities]
    written = [_private(users, "\n".join(lines) + "\n")]
    for name, conf in lab_configs(lab, users.resolve()).items():
        written.append(_private(out / f"{name}.json5", json.dumps(conf, indent=2) + "\n"))
    return written


def _private(path: Path, text: str) -> Path:
    """Writes ``text`` to ``path`` readable by its owner only, atomically: a new file (mode 0600
    from the start) renamed over the old, so no reader sees a partial file and an old file's
    looser mode never holds the new passwords."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _host(endpoint: str) -> str:
    addr = endpoint.split("/", 1)[1]
    return addr.rsplit(":", 1)[0].strip("[]")


def make_certs(lab: Lab, days: int = 825) -> None:
    """Creates the lab's CA and the server's certificate (for the endpoint's host name, plus
    localhost and 127.0.0.1 for the server's own services) with ``openssl``, where missing."""
    if lab.certificate.is_file() and lab.private_key.is_file() and lab.ca_certificate.is_file():
        return
    ca_key = lab.ca_certificate.with_name(lab.ca_certificate.stem + "-key.pem")
    for f in (lab.ca_certificate, lab.certificate, lab.private_key):
        f.parent.mkdir(parents=True, exist_ok=True)

    def run(*args: str, stdin: str | None = None) -> None:
        # umask 077: a private key is the owner's alone from the instant openssl creates it (a
        # chmod afterwards would leave a moment in which others could read it).
        try:
            subprocess.run(["openssl", *args], check=True, capture_output=True, text=True, input=stdin, umask=0o077)
        except FileNotFoundError:
            raise InvalidInputError("openssl is not installed: create the certificates yourself") from None
        except subprocess.CalledProcessError as exc:
            raise InvalidInputError(f"openssl {args[0]} failed: {exc.stderr.strip()}") from None

    if not lab.ca_certificate.is_file():
        run("req", "-x509", "-newkey", "rsa:3072", "-nodes", "-keyout", str(ca_key), "-out", str(lab.ca_certificate),
            "-days", str(days), "-subj", "/CN=DHG lab CA")  # fmt: skip
        os.chmod(ca_key, 0o600)  # also where openssl rewrote a key file that was there, keeping its mode
        os.chmod(lab.ca_certificate, 0o644)  # a certificate is public: every member gets a copy
    host = _host(lab.endpoint)
    alt = {
        "DNS:localhost",
        "IP:127.0.0.1",
        f"IP:{host}" if re.fullmatch(r"[0-9.]+|[0-9a-fA-F:]+", host) else f"DNS:{host}",
    }
    csr = lab.certificate.with_suffix(".csr")
    run(
        "req",
        "-newkey",
        "rsa:3072",
        "-nodes",
        "-keyout",
        str(lab.private_key),
        "-out",
        str(csr),
        "-subj",
        f"/CN={host}",
    )
    os.chmod(lab.private_key, 0o600)
    ext = (
        f"subjectAltName={','.join(sorted(alt))}\nbasicConstraints=CA:FALSE\n"
        "keyUsage=digitalSignature,keyEncipherment\n"
    )
    ext_file = csr.with_suffix(".ext")
    ext_file.write_text(ext)
    run("x509", "-req", "-in", str(csr), "-CA", str(lab.ca_certificate), "-CAkey", str(ca_key), "-CAcreateserial",
        "-out", str(lab.certificate), "-days", str(days), "-extfile", str(ext_file))  # fmt: skip
    os.chmod(lab.certificate, 0o644)
    csr.unlink()
    ext_file.unlink()
