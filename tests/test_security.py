"""Spoofing and transport security, with real zenoh sessions on loopback.

- a rogue queryable answering calibration queries (with a newer t_us and c = 0.999) no longer
  wins `evcal query`: disagreeing instances are refused unless one is named, and
  ``--verify KEY.pub`` accepts only answers signed with the service's key;
- mutual TLS: with certificates from a test CA, a client with a certificate reaches the
  service, one without (or with one of another CA) does not.
"""

from __future__ import annotations

import datetime
import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("zenoh")
pytest.importorskip("cryptography")

from evcal.calibration import Calibration  # noqa: E402
from evcal.io.calibfile import calibration_npz_bytes  # noqa: E402
from evcal.online import OnEIConfig  # noqa: E402
from evcal.service import keys  # noqa: E402
from evcal.service.core import ServiceConfig  # noqa: E402
from evcal.service.server import run  # noqa: E402
from evcal.service.signing import (  # noqa: E402
    SignatureError,
    Signer,
    Verifier,
    generate_keys,
)
from evcal.service.transport import Transport, TransportError, ZenohOptions  # noqa: E402
from evcal.sim.ideal import SimConfig, simulate_ideal  # noqa: E402
from evcal.testing import endpoint, free_port, run_client, wait_for  # noqa: E402

pytestmark = pytest.mark.timeout(180)


def test_signatures_bind_bytes_key_and_instance(tmp_path):
    key, pub = generate_keys(tmp_path / "svc")
    signer = Signer.from_file("svc-a", key)
    v = Verifier(pub)
    payload = b"calibration bytes"
    att = signer.attachment("evcal/cam0/calibration", payload)
    assert v.verify("evcal/cam0/calibration", payload, att) == "svc-a"
    with pytest.raises(SignatureError, match="does not match"):
        v.verify("evcal/cam0/calibration", payload + b"x", att)
    with pytest.raises(SignatureError, match="does not match"):
        v.verify("evcal/cam1/calibration", payload, att)  # replayed on another camera
    with pytest.raises(SignatureError, match="not signed"):
        v.verify("evcal/cam0/calibration", payload, Signer("svc-a").attachment("k", payload))
    other_key, _ = generate_keys(tmp_path / "rogue")
    forged = Signer.from_file("svc-a", other_key).attachment("evcal/cam0/calibration", payload)
    with pytest.raises(SignatureError, match="signed with key"):
        v.verify("evcal/cam0/calibration", payload, forged)
    with pytest.raises(SignatureError, match="exists"):
        generate_keys(tmp_path / "svc")  # never overwrites a key
    assert (tmp_path / "svc.key").stat().st_mode & 0o077 == 0


def test_pinned_keys_round_trip_and_a_damaged_file_says_so(tmp_path, monkeypatch):
    from evcal.service.signing import KnownServices, default_known_services

    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "xdg"))
    assert default_known_services() == tmp_path / "xdg" / "evcal" / "known_services"
    _, pub = generate_keys(tmp_path / "svc")
    known = KnownServices()
    assert known.get("evcal") is None  # no file yet
    known.pin("evcal", Verifier(pub), "good")
    assert known.get("evcal").key_id == Verifier(pub).key_id
    assert known.get("other") is None
    assert (tmp_path / "xdg" / "evcal").stat().st_mode & 0o077 == 0
    known.path.write_text("{")
    with pytest.raises(SignatureError, match="not JSON .*fix or delete it"):
        known.get("evcal")
    known.path.write_text(json.dumps({"evcal": {"key": "!!"}}))
    with pytest.raises(SignatureError, match="no valid key"):
        known.get("evcal")


@pytest.fixture
def signed_service(tmp_path):
    """A service (in this process) with a signing key, fed one short simulated camera."""
    key, pub = generate_keys(tmp_path / "svc")
    ep = endpoint(free_port())
    stop, ready = threading.Event(), threading.Event()
    th = threading.Thread(target=run, args=(
        ZenohOptions.loopback(listen=[ep]),
        ServiceConfig(instance="good", onei=OnEIConfig(n_small=3000, n_large=10**6))),
        kwargs={"stop": stop, "ready": lambda s: ready.set(), "sign_key": key})
    th.start()
    try:
        assert ready.wait(30)
        sim = simulate_ideal(SimConfig(height=24, width=32, duration_s=1.5, seed=3))
        from evcal.clients.replay import replay

        with Transport(ZenohOptions.loopback(connect=[ep])) as t:
            replay(t, sim.recording, "cam0", speed=None)
            wait_for(lambda: any(r.ok for r in t.get("evcal/cam0/calibration")),
                     timeout_s=30, what="a calibration")
            yield {"ep": ep, "pub": pub, "t": t, "tmp": tmp_path}
    finally:
        stop.set()
        th.join(60)


def _rogue(t: Transport, shape: tuple[int, int], *, instance: str = "good",
           key: Path | None = None) -> None:
    """A queryable answering like a service, with c = 0.999 and a far newer t_us; it names
    the genuine instance ("good") unless told otherwise, signed with ``key`` if given."""
    fake = Calibration.uniform(shape, 0.999, 0.0, method="onei", log_offset=30.0)
    payload = calibration_npz_bytes(fake, extra={"t_us": 2**62})
    signer = Signer.from_file(instance, key)

    def answer(req):
        req.reply("evcal/cam0/calibration", payload, keys.ENC_CALIBRATION_NPZ,
                  attachment=signer.attachment("evcal/cam0/calibration", payload))

    t.queryable("evcal/cam0/calibration", answer)


def _genuine(out: Path) -> bool:
    with np.load(out) as z:
        return (float(z["contrast"].max()) < 0.9  # not the rogue's 0.999
                and json.loads(str(z["params_json"]))["t_us"] < 2**62)


def test_a_rogue_answer_does_not_win_the_query(signed_service, monkeypatch):
    """The reported case: a rogue queryable naming the genuine instance with a newer t_us
    won `evcal query` without --verify (exit 0, the rogue's maps). Now query trusts the
    service's key on first use and nothing unsigned or signed by another key after."""
    tmp = signed_service["tmp"]
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp / "xdg"))  # the children's default pin file
    known = tmp / "xdg" / "evcal" / "known_services"
    ep, out = signed_service["ep"], tmp / "cal.npz"
    ep_rogue = endpoint(free_port())
    # the rogue is a peer of its own on the same network: the client reaches both
    zargs = ["--no-multicast-scouting", "--connect", ep, "--connect", ep_rogue, "--camera",
             "cam0", "--out", str(out)]
    with Transport(ZenohOptions.loopback(listen=[ep_rogue])) as rogue:
        _rogue(rogue, (24, 32))  # unsigned, as instance "good"
        # first use: the signed answer wins (the unsigned one is ignored), its key is pinned
        res = run_client("query", zargs)
        assert res.returncode == 0, res.stderr
        assert _genuine(out), res.stderr
        assert "pinned for 'evcal' on first use" in res.stderr
        assert known.is_file()
        assert json.loads(known.read_text())["evcal"]["key_id"] == \
            Verifier(signed_service["pub"]).key_id
        out.unlink()
        res = run_client("query", zargs)
        assert res.returncode == 0, res.stderr
        assert _genuine(out)
        assert "signed with the key pinned for 'evcal'" in res.stderr
        out.unlink()
        # --insecure takes unsigned answers, but two naming one instance disagree: refused
        res = run_client("query", [*zargs, "--insecure"])
        assert res.returncode == 1, res.stderr
        assert "two answers claim instance 'good'" in res.stderr
        assert not out.exists()
        # --verify keeps only the answer signed with the service's key, as before
        res = run_client("query", [*zargs, "--verify", str(signed_service["pub"])])
        assert res.returncode == 0, res.stderr
        assert _genuine(out)
        assert "signature verified" in res.stderr
        assert "instance good" in res.stderr
        out.unlink()
    # a rogue signing with a key of its own, in the genuine instance's name: the pinned key
    # differs, and the query fails saying so (whatever the genuine answer)
    rogue_key, _ = generate_keys(tmp / "rogue")
    with Transport(ZenohOptions.loopback(listen=[ep_rogue])) as rogue:
        _rogue(rogue, (24, 32), key=rogue_key)
        res = run_client("query", zargs)
        assert res.returncode == 1, res.stderr
        assert "is pinned for prefix 'evcal'" in res.stderr
        assert str(known) in res.stderr
        assert not out.exists()
        # another pin file knows nothing: two keys and no pin, refused too
        res = run_client("query", [*zargs, "--known-keys", str(tmp / "other")])
        assert res.returncode == 1, res.stderr
        assert "2 different keys" in res.stderr
    # the rogue's answer alone: unsigned, and the service's key is pinned: refused
    with Transport(ZenohOptions.loopback(listen=[ep_rogue])) as rogue, \
            Transport(ZenohOptions.loopback(connect=[ep_rogue])) as client:
        _rogue(rogue, (24, 32))
        from evcal.clients.query import QueryError, fetch_calibration_npz
        from evcal.service.signing import KnownServices

        wait_for(lambda: any(r.ok for r in client.get("evcal/cam0/calibration")),
                 timeout_s=10, what="the rogue's answer")
        with pytest.raises(QueryError, match="not signed"):
            fetch_calibration_npz(client, "cam0", known=KnownServices(known))
        with pytest.raises(QueryError, match="not signed"):
            fetch_calibration_npz(client, "cam0", verifier=Verifier(signed_service["pub"]))


# ----------------------------------------------------------------------------- mutual TLS


def _ca_and_certs(d: Path, roles: tuple[str, ...] = ("server", "client")
                  ) -> dict[str, Path]:
    """A test CA with a certificate for each role (CN ``evcal-<role>``, valid for localhost and
    127.0.0.1), and a second CA with its own ``rogue_client`` certificate (the wrong one)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    now = datetime.datetime.now(datetime.timezone.utc)

    def name(cn: str) -> x509.Name:
        return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])

    def write_key(key, path: Path) -> Path:
        path.write_bytes(key.private_bytes(serialization.Encoding.PEM,
                                           serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))
        return path

    def cert(subject: str, key, issuer: str, issuer_key, *, ca: bool, san: bool) -> bytes:
        b = (x509.CertificateBuilder().subject_name(name(subject)).issuer_name(name(issuer))
             .public_key(key.public_key()).serial_number(x509.random_serial_number())
             .not_valid_before(now - datetime.timedelta(days=1))
             .not_valid_after(now + datetime.timedelta(days=2))
             .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True))
        if san:
            import ipaddress

            b = b.add_extension(x509.SubjectAlternativeName(
                [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
                critical=False)
        return b.sign(issuer_key, hashes.SHA256()).public_bytes(serialization.Encoding.PEM)

    out: dict[str, Path] = {}
    for ca_name in ("ca", "other_ca"):
        ca_key = ec.generate_private_key(ec.SECP256R1())
        (d / f"{ca_name}.pem").write_bytes(cert(ca_name, ca_key, ca_name, ca_key, ca=True,
                                                san=False))
        out[ca_name] = d / f"{ca_name}.pem"
        for who in (roles if ca_name == "ca" else ("client",)):
            k = ec.generate_private_key(ec.SECP256R1())
            stem = who if ca_name == "ca" else f"rogue_{who}"
            out[f"{stem}_key"] = write_key(k, d / f"{stem}.key")
            (d / f"{stem}.pem").write_bytes(cert(f"evcal-{who}", k, ca_name, ca_key,
                                                 ca=False, san=True))
            out[f"{stem}_cert"] = d / f"{stem}.pem"
    return out


def _tls(ca: Path, cert: Path | None, key: Path | None, *, listen: str = "",
         connect: str = "") -> ZenohOptions:
    extra = [("transport/link/tls/root_ca_certificate", json.dumps(str(ca))),
             ("transport/link/tls/enable_mtls", "true")]
    if cert is not None and key is not None:
        if listen:
            extra += [("transport/link/tls/listen_certificate", json.dumps(str(cert))),
                      ("transport/link/tls/listen_private_key", json.dumps(str(key)))]
        else:
            extra += [("transport/link/tls/connect_certificate", json.dumps(str(cert))),
                      ("transport/link/tls/connect_private_key", json.dumps(str(key)))]
    return ZenohOptions(mode="peer", listen=(listen,) if listen else (),
                        connect=(connect,) if connect else (), multicast_scouting=False,
                        extra=tuple(extra))


def _reaches(opts: ZenohOptions, key: str) -> bool:
    try:
        with Transport(opts) as t:
            return any(r.ok for r in t.get(key, timeout_s=3.0))
    except TransportError:
        return False


def test_mutual_tls_refuses_a_client_without_the_right_certificate(tmp_path):
    c = _ca_and_certs(tmp_path)
    port = free_port()
    listen = f"tls/127.0.0.1:{port}"
    server = _tls(c["ca"], c["server_cert"], c["server_key"], listen=listen)
    connect = f"tls/localhost:{port}"
    with Transport(server) as t:
        t.queryable("evcal/probe", lambda req: req.reply(
            "evcal/probe", b"ok", keys.ENC_STATUS))
        good = _tls(c["ca"], c["client_cert"], c["client_key"], connect=connect)
        wait_for(lambda: _reaches(good, "evcal/probe"), timeout_s=30,
                 what="a client with a certificate of the CA")
        # no certificate at all
        assert not _reaches(_tls(c["ca"], None, None, connect=connect), "evcal/probe")
        # a certificate of another CA
        assert not _reaches(_tls(c["ca"], c["rogue_client_cert"], c["rogue_client_key"],
                                 connect=connect), "evcal/probe")
        # and plain TCP to a TLS port gets nothing either
        assert not _reaches(ZenohOptions.loopback(connect=[f"tcp/127.0.0.1:{port}"]),
                            "evcal/probe")


# ----------------------------------------------------------------------------- access control

ROOT = Path(__file__).resolve().parents[1]


def test_the_shipped_access_control_lets_each_role_do_only_its_job(tmp_path):
    """docker/zenoh/secure/router.json5 in a Python router (mutual TLS, its ACL): a rig puts
    its own cameras' inputs, only the service publishes and answers calibrations, clients
    read."""
    import zenoh

    conf_path = ROOT / "docker" / "zenoh" / "secure" / "router.json5"
    if not conf_path.is_file():
        pytest.skip("not running from a source checkout")
    c = _ca_and_certs(tmp_path, ("router", "rig-rig1", "service", "client"))
    port = free_port()
    conf = zenoh.Config.from_file(str(conf_path))
    conf.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
    for k, v in (("root_ca_certificate", c["ca"]), ("listen_certificate", c["router_cert"]),
                 ("listen_private_key", c["router_key"]),
                 ("connect_certificate", c["router_cert"]),
                 ("connect_private_key", c["router_key"])):
        conf.insert_json5(f"transport/link/tls/{k}", json.dumps(str(v)))

    def client(role: str) -> ZenohOptions:
        opts = _tls(c["ca"], c[f"{role}_cert"], c[f"{role}_key"],
                    connect=f"tls/localhost:{port}")
        return ZenohOptions(mode="client", connect=opts.connect, multicast_scouting=False,
                            extra=opts.extra)

    got: dict[str, list[bytes]] = {"service": [], "client": []}
    cal = "evcal/lab/rig1/cam0/calibration"
    with zenoh.open(conf), Transport(client("service")) as svc, \
            Transport(client("rig-rig1")) as rig, Transport(client("client")) as cli:
        svc.subscribe("evcal/**/events", lambda k, p, e: got["service"].append(p))
        svc.queryable(cal, lambda req: req.reply(cal, b"genuine", keys.ENC_CALIBRATION))
        cli.subscribe("evcal/**/calibration", lambda k, p, e: got["client"].append(p))
        wait_for(lambda: any(r.ok and r.payload == b"genuine"
                             for r in cli.get(cal, timeout_s=2.0)),
                 timeout_s=30, what="the client's query answered by the service")
        # the rig sees the service's subscriber (a publisher that sees none sends nothing)
        own = rig.publisher("evcal/lab/rig1/cam0/events", keys.ENC_EVENTS)
        wait_for(lambda: own.has_subscribers, timeout_s=20,
                 what="the service's subscriber, seen by the rig")
        wait_for(lambda: own.put(b"ev") or got["service"], timeout_s=20,
                 what="a rig's events reaching the service")
        svc.put(cal, b"from-service", keys.ENC_CALIBRATION)
        wait_for(lambda: got["client"], timeout_s=10, what="the service's calibration")
        # what each role may not do: a rig feeding another rig's camera, a rig publishing
        # or answering calibrations, a client putting events
        rig.put("evcal/lab/rig2/cam0/events", b"other-rig", keys.ENC_EVENTS)
        rig.put(cal, b"spoof", keys.ENC_CALIBRATION)
        cli.put("evcal/lab/rig1/cam0/events", b"client-events", keys.ENC_EVENTS)
        rig.queryable("evcal/lab/rig1/cam1/calibration", lambda req: req.reply(
            "evcal/lab/rig1/cam1/calibration", b"rogue", keys.ENC_CALIBRATION))
        import time

        time.sleep(1.0)
        assert b"spoof" not in got["client"], got["client"]
        assert b"client-events" not in got["service"]
        assert b"other-rig" not in got["service"]
        assert not [r for r in cli.get("evcal/lab/rig1/cam1/calibration", timeout_s=2.0)
                    if r.ok]


def test_the_secure_compose_setup_is_consistent(tmp_path):
    """docker/compose.secure.yaml: its commands parse, its zenoh configs load with mutual TLS
    and a deny-by-default ACL, and docker/make-certs.sh makes certificates whose common names
    are the ACL's subjects and that pass a real mutual-TLS handshake."""
    import shutil
    import subprocess

    import zenoh

    yaml = pytest.importorskip("yaml")
    docker = ROOT / "docker"
    if not (docker / "compose.secure.yaml").is_file():
        pytest.skip("not running from a source checkout")
    compose = yaml.safe_load((docker / "compose.secure.yaml").read_text())
    from evcal.service.cli import build_parser as serve_parser

    serve = compose["services"]["evcal"]["command"]
    args = serve_parser().parse_args(serve[1:])
    assert args.sign_key
    assert args.config.endswith("zenoh-client.json5")
    for svc in compose["services"].values():
        for vol in svc.get("volumes", []):
            src = vol.split(":")[0]
            if src.startswith("./zenoh"):
                assert (docker / src).is_file(), vol
    router = zenoh.Config.from_file(str(docker / "zenoh" / "secure" / "router.json5"))
    client = zenoh.Config.from_file(str(docker / "zenoh" / "secure" / "client.json5"))
    for conf in (router, client):
        assert json.loads(conf.get_json("transport/link/tls/enable_mtls")) is True
    acl = json.loads(router.get_json("access_control"))
    assert acl["enabled"]
    assert acl["default_permission"] == "deny"
    cns = {cn for s in acl["subjects"] for cn in s.get("cert_common_names", [])}
    assert cns == {"evcal-rig-rig1", "evcal-service", "evcal-client", "evcal-operator"}
    if shutil.which("openssl") is None:
        pytest.skip("no openssl to run docker/make-certs.sh")
    out = tmp_path / "certs"
    res = subprocess.run(["bash", str(docker / "make-certs.sh"), str(out)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    from cryptography import x509

    made = {x509.load_pem_x509_certificate((out / f"{r}.pem").read_bytes()).subject
            .rfc4514_string() for r in ("rig-rig1", "service", "client", "operator")}
    assert made == {f"CN={cn}" for cn in cns}
    port = free_port()
    server = _tls(out / "ca.pem", out / "router.pem", out / "router.key",
                  listen=f"tls/127.0.0.1:{port}")
    with Transport(server) as t:
        t.queryable("evcal/probe", lambda req: req.reply("evcal/probe", b"ok",
                                                         keys.ENC_STATUS))
        rig = _tls(out / "ca.pem", out / "rig-rig1.pem", out / "rig-rig1.key",
                   connect=f"tls/localhost:{port}")
        wait_for(lambda: _reaches(rig, "evcal/probe"), timeout_s=30,
                 what="a rig with make-certs.sh's certificate")


def test_a_rig_replays_to_its_own_cameras_through_the_shipped_router(tmp_path):
    """The secure set-up as deployed, on loopback: docker/make-certs.sh's certificates, a
    router with docker/zenoh/secure/router.json5, the service and `evcal replay` with
    docker/zenoh/secure/client.json5. Before the fix the rig saw no subscriber (replay exit
    3, "nobody subscribes") and a rig certificate could feed any camera."""
    import shutil
    import subprocess

    import zenoh

    from evcal.clients.replay import EXIT_UNCONFIRMED, exit_code, replay
    from evcal.io import write_recording

    if shutil.which("openssl") is None:
        pytest.skip("no openssl to run docker/make-certs.sh")
    docker = ROOT / "docker"
    if not (docker / "make-certs.sh").is_file():
        pytest.skip("not running from a source checkout")
    certs = tmp_path / "certs"
    res = subprocess.run(["bash", str(docker / "make-certs.sh"), str(certs)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    port = free_port()
    conf = zenoh.Config.from_file(str(docker / "zenoh" / "secure" / "router.json5"))
    conf.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
    for k, v in (("root_ca_certificate", "ca.pem"), ("listen_certificate", "router.pem"),
                 ("listen_private_key", "router.key")):
        conf.insert_json5(f"transport/link/tls/{k}", json.dumps(str(certs / v)))
    client_conf = str(docker / "zenoh" / "secure" / "client.json5")

    def tls(role: str) -> tuple[tuple[str, str], ...]:
        """client.json5's settings for this machine: the router's port, the role's files."""
        return (("connect/endpoints", json.dumps([f"tls/localhost:{port}"])),
                ("transport/link/tls/root_ca_certificate", json.dumps(str(certs / "ca.pem"))),
                ("transport/link/tls/connect_certificate",
                 json.dumps(str(certs / f"{role}.pem"))),
                ("transport/link/tls/connect_private_key",
                 json.dumps(str(certs / f"{role}.key"))))

    def as_client(role: str) -> ZenohOptions:
        return ZenohOptions(config_file=client_conf, extra=tls(role))

    rec = simulate_ideal(SimConfig(height=24, width=32, duration_s=1.0, seed=3)).recording
    path = write_recording(rec, tmp_path / "sim.npz")
    stop, ready = threading.Event(), threading.Event()
    with zenoh.open(conf):
        th = threading.Thread(target=run, args=(
            as_client("service"),
            ServiceConfig(instance="good", onei=OnEIConfig(n_small=3000, n_large=10**6))),
            kwargs={"stop": stop, "ready": lambda s: ready.set()})
        th.start()
        try:
            assert ready.wait(30)
            cli = ["--config", client_conf]
            for k, v in tls("rig-rig1"):
                cli += ["--cfg", f"{k}:{v}"]
            res = run_client("replay", [str(path), "--camera", "lab/rig1/cam0", "--max-rate",
                                        "--wait-subscriber", "10", *cli])
            assert res.returncode == 0, res.stderr
            assert "the service processed 100 event messages" in res.stderr, res.stderr
            # another rig's camera: the router drops the puts, the status stays hidden, so
            # no service confirms delivery (replay would ask for --confirm-timeout, 60 s)
            with Transport(as_client("rig-rig1")) as t:
                t0 = time.monotonic()
                stats = replay(t, rec, "lab/rig2/cam0", speed=None, wait_subscriber_s=10,
                               confirm_timeout_s=3.0)
                assert time.monotonic() - t0 < 30
            assert stats.subscribed
            assert stats.delivered is None
            assert not stats.confirmed
            assert exit_code(stats) == EXIT_UNCONFIRMED, stats.why_unconfirmed
            # a client certificate feeds nothing and sees no input subscriber
            with Transport(as_client("client")) as t:
                stats = replay(t, rec, "lab/rig1/cam1", speed=None, wait_subscriber_s=1)
                assert not stats.subscribed
                cams = json.loads(t.get("evcal/cameras", timeout_s=5.0)[0].payload)
            assert [c["id"] for c in cams["cameras"]] == ["lab/rig1/cam0"]
        finally:
            stop.set()
            th.join(60)
