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


def _rogue(t: Transport, shape: tuple[int, int]) -> None:
    """A queryable answering like a service, with c = 0.999 and a far newer t_us."""
    fake = Calibration.uniform(shape, 0.999, 0.0, method="onei", log_offset=30.0)
    payload = calibration_npz_bytes(fake, extra={"t_us": 2**62})

    def answer(req):
        req.reply("evcal/cam0/calibration", payload, keys.ENC_CALIBRATION_NPZ,
                  attachment=Signer("rogue").attachment("evcal/cam0/calibration", payload))

    t.queryable("evcal/cam0/calibration", answer)


def test_a_rogue_answer_does_not_win_the_query(signed_service):
    # the rogue is a peer of its own on the same network: the client reaches both
    ep, out = signed_service["ep"], signed_service["tmp"] / "cal.npz"
    ep_rogue = endpoint(free_port())
    zargs = ["--no-multicast-scouting", "--connect", ep, "--connect", ep_rogue, "--camera",
             "cam0", "--out", str(out)]
    with Transport(ZenohOptions.loopback(listen=[ep_rogue])) as rogue:
        _rogue(rogue, (24, 32))
        # two instances disagree: refused, and the message says how to choose
        res = run_client("query", zargs)
        assert res.returncode == 1, res.stderr
        assert "different calibrations" in res.stderr and "--instance" in res.stderr
        assert not out.exists()
        # --verify keeps only the answer signed with the service's key
        res = run_client("query", [*zargs, "--verify", str(signed_service["pub"])])
        assert res.returncode == 0, res.stderr
        assert "signature verified" in res.stderr and "instance good" in res.stderr
        with np.load(out) as z:
            assert float(z["contrast"].max()) < 0.9  # not the rogue's 0.999
            assert json.loads(str(z["params_json"]))["t_us"] < 2**62
        # naming an instance works too (without cryptographic proof)
        out.unlink()
        res = run_client("query", [*zargs, "--instance", "good"])
        assert res.returncode == 0, res.stderr
    # the rogue's answer alone, with --verify: refused, saying why
    with Transport(ZenohOptions.loopback(listen=[ep_rogue])) as rogue, \
            Transport(ZenohOptions.loopback(connect=[ep_rogue])) as client:
        _rogue(rogue, (24, 32))
        from evcal.clients.query import QueryError, fetch_calibration_npz

        wait_for(lambda: any(r.ok for r in client.get("evcal/cam0/calibration")),
                 timeout_s=10, what="the rogue's answer")
        with pytest.raises(QueryError, match="not signed"):
            fetch_calibration_npz(client, "cam0", verifier=Verifier(signed_service["pub"]))


# ----------------------------------------------------------------------------- mutual TLS


def _ca_and_certs(d: Path) -> dict[str, Path]:
    """A test CA, a server certificate for 127.0.0.1 and a client certificate; and a second
    CA with its own client certificate (the wrong one)."""
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
        for who in (("server", "client") if ca_name == "ca" else ("client",)):
            k = ec.generate_private_key(ec.SECP256R1())
            stem = who if ca_name == "ca" else f"rogue_{who}"
            out[f"{stem}_key"] = write_key(k, d / f"{stem}.key")
            (d / f"{stem}.pem").write_bytes(cert(f"evcal-{stem}", k, ca_name, ca_key,
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
