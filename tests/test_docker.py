"""The docker deployment: compose file, zenoh configs and Dockerfile are consistent.

No Docker engine runs here: ``docker compose config`` runs where the compose client exists,
the rest checks the files themselves (they parse; every path they name exists; the commands
they run parse with evcal's own argument parsers).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCKER = ROOT / "docker"
COMPOSE = DOCKER / "compose.yaml"


def compose_client() -> list[str] | None:
    docker = shutil.which("docker")
    if docker and subprocess.run([docker, "compose", "version"], capture_output=True,
                                 timeout=30).returncode == 0:
        return [docker, "compose"]
    legacy = shutil.which("docker-compose")
    return [legacy] if legacy else None


def test_docker_compose_config():
    client = compose_client()
    if client is None:
        pytest.skip("no docker compose client on this machine")
    res = subprocess.run([*client, "-f", str(COMPOSE), "config", "--quiet"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr


@pytest.fixture(scope="module")
def compose():
    yaml = pytest.importorskip("yaml")
    return yaml.safe_load(COMPOSE.read_text())


def test_compose_services_and_paths(compose):
    services = compose["services"]
    assert set(services) == {"router", "evcal", "replay"}
    assert services["router"]["image"].startswith("eclipse/zenoh:")
    build = services["evcal"]["build"]
    assert (DOCKER / build["context"] / build["dockerfile"]).is_file()
    for svc in services.values():
        for vol in svc.get("volumes", []):
            src = vol.split(":")[0]
            if src.startswith("${"):
                continue  # a host folder chosen by the user
            if src.startswith("."):
                assert (DOCKER / src).is_file(), vol
            else:
                assert src in compose["volumes"], vol


def test_compose_commands_parse(compose):
    from evcal.service.cli import build_parser as serve_parser

    cmd = compose["services"]["evcal"]["command"]
    assert cmd[0] == "serve"
    args = serve_parser().parse_args(cmd[1:])
    assert args.state_dir == "/state"
    assert args.rrd
    pytest.importorskip("zenoh")
    from evcal.clients.replay import build_parser as replay_parser

    cmd = compose["services"]["replay"]["command"]
    assert cmd[0] == "replay"
    args = replay_parser().parse_args(cmd[1:])
    assert args.camera == "lab/rig1/cam0"
    assert args.loop


def test_zenoh_configs_load():
    zenoh = pytest.importorskip("zenoh")
    router = zenoh.Config.from_file(str(DOCKER / "zenoh" / "router.json5"))
    client = zenoh.Config.from_file(str(DOCKER / "zenoh" / "client.json5"))
    # get_json returns JSON text
    assert json.loads(router.get_json("mode")) == "router"
    assert json.loads(client.get_json("mode")) == "client"
    assert json.loads(client.get_json("connect/endpoints")) == ["tcp/router:7447"]


def test_dockerfile_copies_existing_paths():
    text = (DOCKER / "Dockerfile").read_text()
    for line in re.findall(r"^COPY (.+)$", text, flags=re.M):
        *sources, _dest = line.split()
        for src in sources:
            assert (ROOT / src).exists(), src
    assert "'.[service]'" in text


def test_each_rig_certificate_feeds_only_its_own_cameras():
    """docker/zenoh/secure/router.json5: inputs are put only under a rig's own cameras
    (CN evcal-rig-NAME: evcal/lab/NAME/**), every subject names certificates (a subject
    without any matches everyone), and the secure compose file's replay feeds a camera of
    the rig whose certificate it mounts. (Before the fix one CN, evcal-rig, put anywhere.)"""
    zenoh = pytest.importorskip("zenoh")
    yaml = pytest.importorskip("yaml")
    conf = zenoh.Config.from_file(str(DOCKER / "zenoh" / "secure" / "router.json5"))
    acl = json.loads(conf.get_json("access_control"))
    rules = {r["id"]: r for r in acl["rules"]}
    subjects = {s["id"]: s for s in acl["subjects"]}
    assert all(s.get("cert_common_names") for s in subjects.values()), subjects
    rigs = set()
    for policy in acl["policies"]:
        cns = {cn for sid in policy["subjects"] for cn in subjects[sid]["cert_common_names"]}
        for rid in policy["rules"]:
            rule = rules[rid]
            feeds = [k for k in rule["key_exprs"] if k.endswith(("/events", "/frames"))]
            if not (feeds and "put" in rule["messages"] and "ingress" in rule["flows"]):
                continue
            assert len(cns) == 1, f"rule {rid!r} lets {sorted(cns)} put inputs"
            (cn,) = cns
            assert cn.startswith("evcal-rig-"), f"{cn} may put inputs"
            name = cn.removeprefix("evcal-rig-")
            assert all(k.startswith(f"evcal/lab/{name}/") for k in feeds), (cn, feeds)
            assert rule["permission"] == "allow"
            rigs.add(name)
    assert rigs == {"rig1"}
    compose = yaml.safe_load((DOCKER / "compose.secure.yaml").read_text())
    replay = compose["services"]["replay"]
    cert = next(v.split(":")[0] for v in replay["volumes"] if v.endswith(":/certs/me.pem:ro"))
    name = Path(cert).stem.removeprefix("rig-")
    camera = replay["command"][replay["command"].index("--camera") + 1]
    assert name in rigs, cert
    assert camera.startswith(f"lab/{name}/"), (cert, camera)
