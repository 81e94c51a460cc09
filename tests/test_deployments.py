"""Two deployments on one host, each started as the README starts one (``evcal serve
--listen tcp/127.0.0.1:PORT``, clients ``--connect`` it, no scouting flag): neither ingests the
other's cameras. Real zenoh sessions on loopback, in separate processes."""

from __future__ import annotations

import argparse
import contextlib
import json

import pytest

pytest.importorskip("zenoh")

from evcal.io import write_recording  # noqa: E402
from evcal.service.cli import build_parser  # noqa: E402
from evcal.service.transport import (  # noqa: E402
    Transport,
    ZenohOptions,
    add_zenoh_arguments,
    options_from_args,
)
from evcal.sim.ideal import SimConfig, simulate_ideal  # noqa: E402
from evcal.testing import (  # noqa: E402
    ServiceProcess,
    endpoint,
    free_port,
    run_client,
    wait_for,
)

pytestmark = pytest.mark.timeout(180)


def _scouting(argv: list[str]) -> bool | None:
    p = argparse.ArgumentParser()
    add_zenoh_arguments(p)
    return options_from_args(p.parse_args(argv)).multicast_scouting


def test_an_endpoint_turns_multicast_scouting_off(monkeypatch):
    for name in ("EVCAL_CONNECT", "EVCAL_LISTEN", "EVCAL_MODE", "EVCAL_ZENOH_CONFIG"):
        monkeypatch.delenv(name, raising=False)
    assert _scouting([]) is None  # zenoh's default: on
    assert _scouting(["--listen", "tcp/127.0.0.1:7447"]) is False
    assert _scouting(["--connect", "tcp/127.0.0.1:7447"]) is False
    assert _scouting(["--no-multicast-scouting"]) is False
    assert _scouting(["--listen", "tcp/127.0.0.1:7447", "--multicast-scouting"]) is True
    monkeypatch.setenv("EVCAL_CONNECT", "tcp/127.0.0.1:7447")
    assert _scouting([]) is False
    with pytest.raises(ValueError, match="contradict"):
        _scouting(["--multicast-scouting", "--no-multicast-scouting"])


def test_serve_help_says_how_deployments_are_kept_apart():
    text = build_parser().format_help()
    assert "Deployments are kept apart" in text.split("options:")[0]  # the description
    assert "Keeping deployments apart" in text


def test_serve_warns_when_scouting_is_on(caplog):
    from evcal.service.cli import warn_if_scouting

    with caplog.at_level("WARNING", logger="evcal.service"):
        assert warn_if_scouting(ZenohOptions(), "evcal")
        assert not warn_if_scouting(ZenohOptions(listen=("tcp/127.0.0.1:7447",),
                                                 multicast_scouting=False), "evcal")
    assert len(caplog.records) == 1
    assert "every evcal process on the local network" in caplog.records[0].getMessage()


def _cameras(ep: str) -> set[str]:
    with Transport(ZenohOptions.loopback(connect=[ep])) as t:
        replies = [r for r in t.get("evcal/cameras", timeout_s=3.0) if r.ok]
    return {c["id"] for r in replies for c in json.loads(r.payload)["cameras"]}


def test_two_readme_deployments_do_not_see_each_others_cameras(tmp_path):
    sim = simulate_ideal(SimConfig(height=24, width=32, duration_s=1.0, seed=3))
    path = write_recording(sim.recording, tmp_path / "sim.npz")
    deployments = {"a": "site/cam-a", "b": "site/cam-b"}
    eps = {name: endpoint(free_port()) for name in deployments}
    procs = {}
    with contextlib.ExitStack() as stack:
        for name in deployments:
            # as the README's walk-through: an endpoint, no scouting flag
            procs[name] = stack.enter_context(ServiceProcess(
                ["--listen", eps[name], "--state-dir", str(tmp_path / f"state-{name}"),
                 "--log-offset", "30", "-v"], log_path=tmp_path / f"serve-{name}.log"))
        for name in deployments:
            with Transport(ZenohOptions.loopback(connect=[eps[name]])) as t:
                wait_for(lambda t=t: t.alive("evcal/@service/*", timeout_s=1.0),
                         timeout_s=60, what=f"service {name}")
        for name, camera in deployments.items():
            res = run_client("replay", [str(path), "--camera", camera,
                                        "--connect", eps[name], "--max-rate"])
            assert res.returncode == 0, res.stderr
        for name, camera in deployments.items():
            assert _cameras(eps[name]) == {camera}, procs[name].log_text()
        for proc in procs.values():
            assert proc.stop() == 0, proc.log_text()
    for proc in procs.values():
        assert "multicast scouting is on" not in proc.log_text()
