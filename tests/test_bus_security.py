"""Bus security: TLS with mutual TLS on loopback, zenoh access control per role, refused configurations."""

from __future__ import annotations

import json
import os
import queue
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from constructaide.app.cli import main as cli_main
from constructaide.errors import UserError
from constructaide.runtime import BusConfig, open_bus
from constructaide.runtime.security import ROLE_PUBLISHES, BusSecurity, load_security, make_certs, may_publish
from schemas import keys
from schemas.messages import NodeError, Photo

ROOT = Path(__file__).resolve().parents[1]
ECHO = Path(__file__).with_name("echo_node.py")
SITE = "t"


@pytest.fixture(scope="module")
def site_toml(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Certificates from `constructaide certs` (roles + camera cam-a) and a site TOML with TLS, mTLS and ACL."""
    d = tmp_path_factory.mktemp("secure")
    assert cli_main(["certs", "--out", str(d / "certs"), "--camera", "cam-a"]) == 0
    toml = d / "site.toml"
    toml.write_text(
        f'[site]\nname = "{SITE}"\n\n[bus.tls]\nca = "certs/ca.pem"\ncerts = "certs"\n\n'
        '[bus.acl]\nenabled = true\ncameras = ["cam-a"]\n'
    )
    return toml


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT)}


def photo(photo_id: str, camera: str = "cam-a") -> tuple[str, Photo]:
    msg = Photo(site=SITE, photo_id=photo_id, camera_id=camera, capture_time_ns=1_700_000_000_000_000_000, data=b"x")
    return keys.key(keys.PHOTO, site=SITE, camera=camera), msg


def test_roles_match_node_outputs() -> None:
    """The ACL's role table is each node's declared outputs (errors aside): one table, checked against the specs."""
    import importlib

    from constructaide.app.cli import NODE_MODULES

    assert set(ROLE_PUBLISHES) == set(NODE_MODULES)
    for name, module in NODE_MODULES.items():
        spec = importlib.import_module(module).SPEC
        declared = {o.key for o in spec.outputs} - {keys.ERRORS}
        assert declared == set(ROLE_PUBLISHES[name]), name
    assert may_publish("render", "constructaide/s/overlay/state4d/p1")
    assert not may_publish("render", "constructaide/s/photo/cam-a")
    assert may_publish("camera-cam-a", "constructaide/s/photo/cam-a", ["cam-a"])
    assert not may_publish("camera-cam-a", "constructaide/s/photo/cam-b", ["cam-a", "cam-b"])
    assert not may_publish("camera-cam-a", "constructaide/s/registration/cam-a/p1", ["cam-a"])
    assert may_publish("register", "constructaide/s/errors") and may_publish("router", "constructaide/s/photo/x")


def test_refused_configurations(site_toml: Path, tmp_path: Path) -> None:
    sec = load_security(site_toml, "render")
    assert sec is not None and sec.acl and sec.mtls and sec.cert.name == "render.pem"
    assert load_security(_write(tmp_path / "plain.toml", '[site]\nname = "x"\n'), "render") is None

    def refused(body: str, role: str = "render") -> str:
        with pytest.raises(UserError) as e:
            load_security(_write(site_toml.parent / "bad.toml", body), role)
        return str(e.value)

    tls = '[bus.tls]\nca = "certs/ca.pem"\ncerts = "certs"\n'
    assert "needs [bus.tls]" in refused("[bus.acl]\nenabled = true\n")
    assert "mtls = true" in refused(tls + "mtls = false\n[bus.acl]\nenabled = true\n")
    assert "not found" in refused('[bus.tls]\nca = "nowhere/ca.pem"\n')
    assert "unknown role" in refused(tls, role="camera-cam-z")
    assert "bad [bus.tls]" in refused(tls + "cipher = 'x'\n")
    other = make_certs(tmp_path / "other", ["render"])[0].parent  # a certificate from another CA
    assert "not signed by the CA" in refused(f'[bus.tls]\nca = "certs/ca.pem"\ncerts = "{other}"\n')
    assert "not the key of" in refused(tls + 'cert = "certs/render.pem"\nkey = "certs/register.key"\n')
    assert "not role 'render'" in refused(tls + 'cert = "certs/register.pem"\nkey = "certs/register.key"\n'
                                          "[bus.acl]\nenabled = true\n")  # fmt: skip
    with pytest.raises(UserError, match="no \\[bus.tls\\] is configured"):
        BusConfig(listen=["tls/127.0.0.1:0"]).zenoh_config()
    with pytest.raises(UserError, match="bypasses TLS"):
        BusConfig(connect=["tcp/127.0.0.1:7447"], security=sec).zenoh_config()


def _write(p: Path, text: str) -> Path:
    p.write_text(text)
    return p


@pytest.mark.zenoh
def test_mtls_refuses_client_without_certificate(site_toml: Path, tmp_path: Path) -> None:
    import zenoh

    router = load_security(site_toml, "router")
    with open_bus(BusConfig(mode="router", listen=["tls/127.0.0.1:0"], security=router)) as hub:
        ep = f"tls/127.0.0.1:{hub.listen_port()}"
        got = hub.collect(keys.site_pattern(SITE))
        for label, tls in (
            ("no certificate", {"root_ca_certificate": str(router.ca)}),
            ("certificate of another CA", _other_ca_tls(tmp_path, router.ca)),
        ):
            c = zenoh.Config()
            c.insert_json5("mode", '"client"')  # a client fails to open when it reaches no router
            c.insert_json5("scouting/multicast/enabled", "false")
            c.insert_json5("connect/endpoints", json.dumps([ep]))
            c.insert_json5("connect/timeout_ms", "2000")
            c.insert_json5("transport/link/tls", json.dumps(tls))
            with pytest.raises(zenoh.ZError, match="Unable to connect"):
                zenoh.open(c).close()
            assert label not in " ".join(k for k, _ in got.items)
        # A session with a certificate of the site's CA joins and is heard.
        with open_bus(BusConfig(connect=[ep], security=load_security(site_toml, "camera-cam-a"))) as cam:
            _publish_until_heard(cam, got, *photo("p1"))


def _other_ca_tls(tmp_path: Path, ca: Path) -> dict[str, str]:
    other = make_certs(tmp_path / "other", ["recorder"])[0].parent
    return {
        "root_ca_certificate": str(ca),
        "enable_mtls": True,
        "connect_certificate": str(other / "recorder.pem"),
        "connect_private_key": str(other / "recorder.key"),
    }


def _publish_until_heard(bus, collector, key: str, msg: Photo, timeout: float = 20.0) -> None:
    """Publish and wait for it (a new link's routes may take a moment: re-publish at most a few times)."""
    for _ in range(int(timeout / 2)):
        bus.publish(key, msg)
        try:
            collector.wait(1, timeout=2.0, where=lambda k, m: getattr(m, "photo_id", None) == msg.photo_id)
            return
        except TimeoutError:
            continue
    raise TimeoutError(f"{key} {msg.photo_id} never heard")


@pytest.mark.zenoh
def test_acl_drops_forbidden_publish_and_reports(site_toml: Path) -> None:
    """Router process with the ACL (its zenoh trace names each denied put); a camera may publish only its own
    photos; a node run as `render` cannot publish registrations: its handler's publish becomes a NodeError."""
    env = {**_env(), "RUST_LOG": "zenoh::net::routing::interceptor::access_control=trace"}
    router = subprocess.Popen(
        [sys.executable, "-m", "constructaide.app.cli", "router", "--bus-security", str(site_toml),
         "--listen", "tls/127.0.0.1:0"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    denied: queue.Queue[str] = queue.Queue()
    listening: queue.Queue[str] = queue.Queue()
    scanners = [
        threading.Thread(
            target=_scan, args=(router.stdout, re.compile(r"CertCommonName.*unauthorized to Put.*"), denied)
        ),
        threading.Thread(target=_scan, args=(router.stderr, re.compile(r"router listening on (\S+)"), listening)),
    ]
    for t in scanners:
        t.start()
    echo = None
    echo_log = (site_toml.parent / f"echo-{os.getpid()}.log").open("w+")
    try:
        ep = listening.get(timeout=30).rstrip(";,")
        assert ep.startswith("tls/127.0.0.1:")
        with (
            open_bus(BusConfig(connect=[ep], security=load_security(site_toml, "recorder"))) as rec,
            open_bus(BusConfig(connect=[ep], security=load_security(site_toml, "camera-cam-a"))) as cam,
        ):
            got = rec.collect(keys.site_pattern(SITE))
            _publish_until_heard(cam, got, *photo("p1"))
            # Our bus refuses what the ACL would drop, naming the key...
            with pytest.raises(PermissionError, match="may not publish on constructaide/t/photo/cam-b"):
                cam.publish(*photo("q1", camera="cam-b"))
            # ...and a session that bypasses the check (raw put) is dropped by the router, which logs it.
            cam.session.put(keys.key(keys.PHOTO, site=SITE, camera="cam-b"), b"forged")
            cam.publish(*photo("p2"))  # same link, after the forged one: once it is here, the forged one is gone
            got.wait(2, timeout=20, where=lambda k, m: isinstance(m, Photo))
            assert [k for k, _ in got.items if k.endswith("/cam-b")] == []
            line = _wait_line(denied, "on constructaide/t/photo/cam-b")
            assert "CertCommonName(camera-cam-a)" in line

            # A node with the `render` role: its registration is refused and reported as a NodeError.
            echo = subprocess.Popen(
                [sys.executable, str(ECHO), "--site", SITE, "--connect", ep, "--bus-security", str(site_toml),
                 "--role", "render"],
                env=_env(), stdout=subprocess.DEVNULL, stderr=echo_log,
            )  # fmt: skip
            rec.wait_for_tokens([keys.pattern(keys.LIVELINESS, site=SITE, node="echo")], timeout=30)
            errors = rec.collect(keys.key(keys.ERRORS, site=SITE))
            # The collector's subscription reaches the router on its own link: a NodeError sent before it arrived
            # is not delivered, so the photo is re-sent until one is heard (the same photo, the same refusal).
            for _ in range(5):
                cam.publish(*photo("p3"))
                try:
                    errors.wait(1, timeout=4)
                    break
                except TimeoutError:
                    continue
            (_, err), *_ = errors.wait(1, timeout=1)
            assert isinstance(err, NodeError) and err.node == "echo"
            assert "role 'render' may not publish on constructaide/t/registration/cam-a/p3" in err.reason
            assert err.key == "constructaide/t/photo/cam-a"
            assert not [k for k, _ in got.items if "/registration/" in k]
            assert echo.poll() is None
    finally:
        hung = [p for p in (echo, router) if p is not None and not _stopped(p)]
        for t in scanners:
            t.join(20)
        for f in (router.stdout, router.stderr):
            if f is not None:
                f.close()
        echo_log.seek(0)
        log = echo_log.read()
        echo_log.close()
    # A node must stop on SIGTERM: one that did not is failed with its threads' stacks (SIGUSR1, faulthandler).
    names = [" ".join(map(str, p.args[1:4])) for p in hung]
    assert not hung, f"did not stop within 20 s of SIGTERM: {names}; echo node's stderr:\n{log}"


def _stopped(p: subprocess.Popen[str]) -> bool:
    """SIGTERM ``p`` and wait 20 s; a process still running then gets SIGUSR1 (its stacks to its stderr) and is
    killed: False."""
    if p.poll() is not None:
        return True
    p.terminate()
    try:
        p.wait(20)
        return True
    except subprocess.TimeoutExpired:
        p.send_signal(signal.SIGUSR1)
        try:
            p.wait(2)
        except subprocess.TimeoutExpired:
            pass
        p.kill()
        p.wait(20)
        return False


def _scan(stream, pattern: re.Pattern[str], out: queue.Queue[str]) -> None:
    for line in stream:
        plain = re.sub(r"\x1b\[[0-9;]*m", "", line)
        m = pattern.search(plain)
        if m:
            out.put(m.group(1) if m.groups() else m.group(0))


def _wait_line(q: queue.Queue[str], needle: str, timeout: float = 20.0) -> str:
    import time

    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        line = q.get(timeout=left)
        if needle in line:
            return line
    raise TimeoutError(needle)


def test_security_json5_shape(site_toml: Path) -> None:
    sec = load_security(site_toml, "ingest")
    assert isinstance(sec, BusSecurity)
    j = sec.json5()
    assert j["transport/link/tls"]["enable_mtls"] is True and j["access_control"]["default_permission"] == "deny"
    cfg = BusConfig(security=sec).zenoh_config()  # embedded hub scheme switches to tls/
    assert "tls/127.0.0.1:" in str(cfg)
