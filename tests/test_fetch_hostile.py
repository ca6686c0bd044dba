"""`spot data fetch` against a hostile HTTP server on 127.0.0.1 (issue 43): endless bodies, a
trickle, redirects across host and scheme, short and long bodies, and a correct body that must
still pass. Each case checks the error names the cause, that no file lands in the destination,
that nothing reaches the trust-on-first-use lock, and (an audit hook) that nothing is written
outside the test's tmp_path. Limits are small parameters, so no case sends more than a few KB to
disk or waits more than about two seconds."""

import hashlib
import json
import os
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
import requests
import tqdm.auto  # noqa: F401 - imported before the audit window (no lazy import writes .pyc then)
import urllib3.exceptions  # noqa: F401

from spot import SpotError
from spot.data import download, fetch, sources
from tests.conftest import run_cli

BODY = bytes(range(256)) * 4  # the file: 1,024 bytes
PIN = len(BODY)


# --------------------------------------------------------------------------- writes outside tmp_path
_WRITES: list[str] | None = None  # paths opened for writing, renamed, removed or made, while a test runs
_WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_APPEND | os.O_TRUNC


def _audit(event: str, args: tuple) -> None:
    if _WRITES is None:
        return
    if event == "open":
        path, mode, flags = args
        if path is None or isinstance(path, int):
            return
        writing = (isinstance(mode, str) and any(c in mode for c in "wax+")) or (
            isinstance(flags, int) and flags & _WRITE_FLAGS
        )
        if writing:
            _WRITES.append(os.path.abspath(os.fsdecode(path)))
    elif event in ("os.rename", "os.remove", "os.mkdir", "os.rmdir", "os.truncate", "os.link", "os.symlink"):
        _WRITES.extend(os.path.abspath(os.fsdecode(a)) for a in args[:2] if isinstance(a, str | bytes | os.PathLike))


sys.addaudithook(_audit)  # cannot be removed; does nothing outside a test of this module


@pytest.fixture(autouse=True)
def confined(tmp_path, monkeypatch):
    """Every write during the test lands under tmp_path."""
    global _WRITES
    monkeypatch.setenv("NO_PROXY", "127.0.0.1,localhost")
    monkeypatch.setenv("no_proxy", "127.0.0.1,localhost")
    _WRITES = []
    try:
        yield
        root = str(tmp_path.resolve())
        outside = [p for p in _WRITES if not (os.path.realpath(p) + os.sep).startswith(root + os.sep)]
        assert outside == [], outside
    finally:
        _WRITES = None


# --------------------------------------------------------------------------- the hostile server
class Hostile:
    """Answers each path with a behaviour: ``routes[path] = (kind, arg)``; logs every request."""

    def __init__(self):
        self.routes: dict[str, tuple[str, object]] = {}
        self.log: list[str] = []
        self.stop = threading.Event()
        outer = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"  # chunked bodies

            def log_message(self, *args):
                pass

            def do_GET(self):
                outer.log.append(self.path)
                kind, arg = outer.routes.get(self.path, ("404", None))
                try:
                    getattr(outer, "_" + kind.replace("-", "_"))(self, arg)
                except (BrokenPipeError, ConnectionResetError):
                    pass  # the client hung up: what a refused transfer does

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.httpd.server_address[1]
        self.base = f"http://127.0.0.1:{self.port}"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self):
        self.stop.set()
        self.httpd.shutdown()
        self.httpd.server_close()

    @staticmethod
    def _head(h, status=200, **headers):
        h.send_response(status)
        for k, v in headers.items():
            h.send_header(k.replace("_", "-"), str(v))
        h.end_headers()

    def _404(self, h, _):
        h.send_error(404)

    def _body(self, h, data):  # a correct answer
        self._head(h, Content_Length=len(data))
        h.wfile.write(data)

    def _redirect(self, h, location):
        self._head(h, 302, Location=location, Content_Length=0)

    def _endless_chunked(self, h, _):
        self._head(h, Transfer_Encoding="chunked")
        for _ in range(50_000):  # at most 50 MB to a socket, never to a disk; the client stops first
            if self.stop.is_set():
                return
            h.wfile.write(b"400\r\n" + b"x" * 1024 + b"\r\n")

    def _endless_unsized(self, h, _):  # no length at all; the body ends when the connection does
        h.close_connection = True
        self._head(h, Connection="close")
        for _ in range(50_000):
            if self.stop.is_set():
                return
            h.wfile.write(b"y" * 1024)

    def _trickle(self, h, pause):  # announces the file, sends one byte per pause
        self._head(h, Content_Length=PIN)
        for i in range(PIN):
            if self.stop.wait(pause):
                return
            h.wfile.write(BODY[i : i + 1])
            h.wfile.flush()

    def _silent(self, h, _):  # headers, then nothing
        self._head(h, Content_Length=PIN)
        h.wfile.flush()
        self.stop.wait(10)

    def _short(self, h, sent):  # announces the whole file, sends `sent` bytes and closes
        h.close_connection = True
        self._head(h, Content_Length=PIN, Connection="close")
        h.wfile.write(BODY[:sent])

    def _unsized(self, h, data):  # the whole body, but no length announced
        h.close_connection = True
        self._head(h, Connection="close")
        h.wfile.write(data)

    def _chunked(self, h, data):  # a finite chunked body, no length announced
        self._head(h, Transfer_Encoding="chunked")
        h.wfile.write(f"{len(data):x}\r\n".encode() + data + b"\r\n0\r\n\r\n")

    def _gzip(self, h, data):
        self._head(h, Content_Length=len(data), Content_Encoding="gzip")
        h.wfile.write(data)


@pytest.fixture
def server():
    s = Hostile()
    yield s
    s.close()


@pytest.fixture
def victim():
    """A second loopback service, holding the very file: a refused redirect must never reach it."""
    s = Hostile()
    s.routes["/toy.hdf5"] = ("body", BODY)
    yield s
    s.close()


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def registry(tmp_path: Path, url: str, trust="third-party", max_size=None, redirect_hosts=None) -> Path:
    entry = {
        "path": "d4rl/toy-v2.hdf5",
        "urls": [url],
        "trust": trust,
        "sha256": None if trust == "tofu" else sha(BODY),
        "size": None if trust == "tofu" else PIN,
    }
    if max_size is not None:
        entry["max_size"] = max_size
    data = {"schema": 1, "sources": {"d4rl/toy-v2": {"kind": "d4rl", "files": [entry]}}}
    if redirect_hosts is not None:
        data["redirect_hosts"] = redirect_hosts
    path = tmp_path / "reg.json"
    path.write_text(json.dumps(data))
    return path


def run(tmp_path, reg, mirrors=(), retries=0, **limits):
    return fetch.fetch(
        "d4rl/toy-v2",
        tmp_path / "dest",
        mirrors=mirrors,
        registry=reg,
        lock=tmp_path / "lock.json",
        progress=False,
        retries=retries,
        backoff=0.0,
        limits=fetch.Limits(**limits) if limits else None,
    )


def refused(tmp_path, reg, mirrors=(), retries=0, **limits) -> str:
    """Run a fetch that must fail; check nothing was kept or recorded; return the message."""
    with pytest.raises(SpotError) as err:
        run(tmp_path, reg, mirrors, retries, **limits)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("could not fetch 'd4rl/toy-v2.hdf5'")
    assert_nothing_kept(tmp_path)
    return msg


def assert_nothing_kept(tmp_path, part_ok=False):
    folder = tmp_path / "dest" / "d4rl"
    left = sorted(p.name for p in folder.iterdir()) if folder.exists() else []
    part = folder / "toy-v2.hdf5.part"
    if part_ok and part.exists():  # a resumable prefix of a pinned file, never more than the pin
        held = part.read_bytes()
        assert len(held) < PIN and held == BODY[: len(held)]
        left.remove(part.name)
    assert left == [], left
    assert not (tmp_path / "lock.json").exists()


# --------------------------------------------------------------------------- a correct body
def test_correct_body_through_a_same_origin_redirect_verifies(tmp_path, server):
    server.routes["/m/d4rl/toy-v2.hdf5"] = ("redirect", "/files/toy.hdf5")  # relative: same origin
    server.routes["/files/toy.hdf5"] = ("body", BODY)
    reg = registry(tmp_path, "https://origin.invalid/toy.hdf5")  # never reached: the mirror serves it
    result = run(tmp_path, reg, mirrors=[server.base + "/m"])
    final = tmp_path / "dest" / "d4rl" / "toy-v2.hdf5"
    assert final.read_bytes() == BODY and result.files[0].sha256 == hashlib.sha256(BODY).hexdigest()
    assert result.files[0].status == "downloaded" and fetch.verify_fetched(final)
    assert server.log == ["/m/d4rl/toy-v2.hdf5", "/files/toy.hdf5"]


def test_correct_body_on_first_use_is_recorded(tmp_path, server):
    server.routes["/toy.hdf5"] = ("body", BODY)
    result = run(tmp_path, registry(tmp_path, server.base + "/toy.hdf5", trust="tofu", max_size=PIN))
    assert result.files[0].status == "recorded"
    rec = json.loads((tmp_path / "lock.json").read_text())["files"]["d4rl/toy-v2:d4rl/toy-v2.hdf5"]
    assert (rec["sha256"], rec["size"]) == (sha(BODY), PIN)


# --------------------------------------------------------------------------- endless bodies
def test_endless_chunked_body_stops_one_byte_past_the_pin(tmp_path, server):
    server.routes["/toy.hdf5"] = ("endless-chunked", None)
    msg = refused(tmp_path, registry(tmp_path, server.base + "/toy.hdf5"))
    assert f"127.0.0.1 sent more than {PIN:,} bytes (the pinned size); stopped at {PIN + 1:,}" in msg


@pytest.mark.parametrize("kind", ["endless-chunked", "endless-unsized"])
def test_endless_body_of_a_first_use_file_stops_at_its_max_size(tmp_path, server, kind):
    server.routes["/toy.hdf5"] = (kind, None)
    msg = refused(tmp_path, registry(tmp_path, server.base + "/toy.hdf5", trust="tofu", max_size=4096))
    assert "sent more than 4,096 bytes (the registry's max_size); stopped at 4,097" in msg


def test_endless_body_without_a_declared_max_stops_at_max_bytes(tmp_path, server):
    server.routes["/toy.hdf5"] = ("endless-chunked", None)
    msg = refused(tmp_path, registry(tmp_path, server.base + "/toy.hdf5", trust="tofu"), max_bytes=3000)
    assert "sent more than 3,000 bytes (the max_bytes limit); stopped at 3,001" in msg


def test_cli_endless_body_is_one_error_line_and_exit_2(tmp_path, server):
    server.routes["/toy.hdf5"] = ("endless-chunked", None)
    reg = registry(tmp_path, server.base + "/toy.hdf5")
    out = run_cli(
        *("data", "fetch", "toy-v2", "--registry", str(reg), "--dest", str(tmp_path / "dest")),
        *("--lock", str(tmp_path / "lock.json"), "--quiet"),
        cwd=tmp_path,
        env={"NO_PROXY": "127.0.0.1", "no_proxy": "127.0.0.1"},
        timeout=120,
    )
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: could not fetch") and f"stopped at {PIN + 1:,}" in lines[0]
    assert_nothing_kept(tmp_path)


# --------------------------------------------------------------------------- slow servers
def test_trickle_fails_at_the_deadline_and_says_what_it_waited_for(tmp_path, server):
    server.routes["/toy.hdf5"] = ("trickle", 0.1)  # 10 bytes/s: every read returns, none times out
    t0 = time.monotonic()
    msg = refused(tmp_path, registry(tmp_path, server.base + "/toy.hdf5", trust="tofu"), deadline=1.0, min_rate=0)
    assert time.monotonic() - t0 < 3.0
    assert "127.0.0.1: the download passed its deadline of 1 s while waiting for the rest of the file" in msg
    assert "bytes so far" in msg and "partial download was deleted" in msg


def test_trickle_of_a_pinned_file_keeps_only_a_resumable_prefix(tmp_path, server):
    server.routes["/toy.hdf5"] = ("trickle", 0.1)
    with pytest.raises(SpotError, match="deadline of 1 s .* bytes so far.*kept for a resume"):
        run(tmp_path, registry(tmp_path, server.base + "/toy.hdf5"), retries=2, deadline=1.0, min_rate=0)
    assert len(server.log) == 1  # the deadline covers the retries: no second attempt
    assert_nothing_kept(tmp_path, part_ok=True)


def test_trickle_fails_the_minimum_rate_and_is_retried_once(tmp_path, server):
    server.routes["/toy.hdf5"] = ("trickle", 0.1)
    t0 = time.monotonic()
    msg = refused(
        tmp_path,
        registry(tmp_path, server.base + "/toy.hdf5", trust="tofu"),
        retries=1,
        deadline=None,
        min_rate=50,
        rate_window=0.5,
    )
    assert time.monotonic() - t0 < 3.0 and len(server.log) == 2
    assert "connection failed 2 times" in msg and "below the minimum of 50 bytes/s" in msg and "127.0.0.1 sent" in msg


def test_silence_after_the_headers_hits_the_read_timeout(tmp_path, server):
    server.routes["/toy.hdf5"] = ("silent", None)
    msg = refused(tmp_path, registry(tmp_path, server.base + "/toy.hdf5", trust="tofu"), read_timeout=0.5)
    assert "127.0.0.1 sent nothing for 0.5 s (0 bytes so far)" in msg


def test_limits_are_checked():
    with pytest.raises(SpotError, match="'read_timeout' is nan"):
        fetch.fetch("d4rl/hopper-medium-v2", limits=fetch.Limits(read_timeout=float("nan")))
    with pytest.raises(SpotError, match="mirror 'file:///srv'"):
        fetch.fetch("d4rl/hopper-medium-v2", mirrors=["file:///srv"])


# --------------------------------------------------------------------------- redirects
@pytest.mark.parametrize(
    "location, hosts, why",
    [
        ("file:///etc/passwd", None, "scheme 'file:'"),
        ("ftp://127.0.0.1/toy.hdf5", None, "scheme 'ftp:'"),
        ("http://169.254.169.254/latest/meta-data/", None, "plain http to another origin"),
        ("http://127.0.0.1:{victim}/toy.hdf5", None, "plain http to another origin"),
        ("http://localhost:{port}/toy.hdf5", None, "plain http to another origin"),
        ("https://127.0.0.1:{victim}/toy.hdf5", None, "127.0.0.1 resolves to 127.0.0.1, a loopback address"),
        ("https://evil.invalid/toy.hdf5", None, "host evil.invalid is neither 127.0.0.1 nor a host"),
        ("https://169.254.169.254/latest/", ["169.254.169.254"], "169.254.169.254, a link-local address"),
        ("https://localhost:{victim}/toy.hdf5", ["localhost"], "a loopback address"),
    ],
)
def test_redirect_is_refused(tmp_path, server, victim, location, hosts, why):
    """The user's mirror is on loopback (allowed: the user named it); where it redirects is not."""
    server.routes["/m/d4rl/toy-v2.hdf5"] = ("redirect", location.format(victim=victim.port, port=server.port))
    reg = registry(tmp_path, "https://origin.invalid/toy.hdf5", trust="tofu", redirect_hosts=hosts)
    msg = refused(tmp_path, reg, mirrors=[server.base + "/m"])
    first = msg.split("; https://origin.invalid")[0]  # the mirror's part (the origin then fails to resolve)
    assert why in first and "refused" in first
    assert victim.log == []  # nothing was asked of the other service


def test_redirect_loop_is_capped(tmp_path, server):
    server.routes["/toy.hdf5"] = ("redirect", "/toy.hdf5")
    msg = refused(tmp_path, registry(tmp_path, server.base + "/toy.hdf5", trust="tofu"), max_redirects=3)
    assert "more than 3 redirects" in msg and len(server.log) == 4


@pytest.mark.parametrize(
    "current, location, allowed",
    [
        ("https://huggingface.co/d/x.hdf5", "http://huggingface.co/d/x.hdf5", False),  # downgrade
        ("https://huggingface.co/d/x.hdf5", "https://cas-bridge.xethub.hf.co/x?sig=1", True),  # declared CDN
        ("https://huggingface.co/d/x.hdf5", "https://hf.co.evil.example/x", False),
        ("https://rail.eecs.berkeley.edu/a.hdf5", "https://rail.eecs.berkeley.edu/b.hdf5", True),
        ("http://rail.eecs.berkeley.edu/a.hdf5", "https://rail.eecs.berkeley.edu/a.hdf5", True),  # upgrade
        ("https://github.com/o/r/raw/c/f", "https://raw.githubusercontent.com/o/r/c/f", True),
        ("https://github.com/o/r/raw/c/f", "data:text/plain,x", False),
        ("https://github.com/o/r/raw/c/f", "https://github.com:99999/x", False),
    ],
)
def test_redirect_rule_of_the_packaged_registry(current, location, allowed):
    policy = download.Policy(sources.declared_hosts(), frozenset(), download.Limits())
    if allowed:
        assert download._redirect_target(current, location, policy).startswith("https://")
    else:
        with pytest.raises(download.Refused, match="refused"):
            download._redirect_target(current, location, policy)


def test_connection_to_a_loopback_address_is_refused_after_the_fact(server):
    """A host name that passed the check but connected to loopback (re-resolved) is refused."""
    server.routes["/toy.hdf5"] = ("body", BODY)
    policy = download.Policy(frozenset(), frozenset(), download.Limits())
    with requests.get(server.base + "/toy.hdf5", stream=True, timeout=5) as r:
        with pytest.raises(download.Refused, match="went to 127.0.0.1, a loopback address"):
            download._check_peer(r, server.base + "/toy.hdf5", policy)


def test_packaged_primary_urls_are_https():
    for source in fetch.load_registry().values():
        for f in source.files:
            assert all(u.startswith("https://") for u in f.urls), f.urls
            assert f.size is not None or f.max_size is not None, f.path


# --------------------------------------------------------------------------- short and long bodies
def test_short_body_of_a_pinned_file_is_never_the_file(tmp_path, server):
    server.routes["/toy.hdf5"] = ("short", 600)
    with pytest.raises(SpotError, match="127.0.0.1 broke off after 600 bytes"):
        run(tmp_path, registry(tmp_path, server.base + "/toy.hdf5"), retries=1)
    assert len(server.log) == 2  # the retry asked again (the server ignores Range and breaks off again)
    assert_nothing_kept(tmp_path, part_ok=True)


def test_short_body_of_a_first_use_file_is_not_recorded(tmp_path, server):
    server.routes["/toy.hdf5"] = ("short", 600)
    msg = refused(tmp_path, registry(tmp_path, server.base + "/toy.hdf5", trust="tofu"))
    assert "broke off after 600 bytes" in msg and "partial download was deleted" in msg


@pytest.mark.parametrize("kind", ["unsized", "chunked"])
def test_first_use_body_without_an_announced_size_is_not_recorded(tmp_path, server, kind):
    server.routes["/toy.hdf5"] = (kind, BODY[:700])  # a cut copy: nothing says it is cut
    msg = refused(tmp_path, registry(tmp_path, server.base + "/toy.hdf5", trust="tofu"))
    assert "announced no size for these 700 bytes" in msg


def test_long_body_announced_over_the_pin_is_not_read(tmp_path, server):
    server.routes["/toy.hdf5"] = ("body", BODY + b"z" * 500)
    msg = refused(tmp_path, registry(tmp_path, server.base + "/toy.hdf5"))
    assert f"announces {PIN + 500} bytes; expected {PIN}" in msg


@pytest.mark.parametrize("kind", ["unsized", "chunked"])
def test_long_unannounced_body_stops_past_the_pin(tmp_path, server, kind):
    server.routes["/toy.hdf5"] = (kind, BODY + b"z" * 5000)
    msg = refused(tmp_path, registry(tmp_path, server.base + "/toy.hdf5"))
    assert f"stopped at {PIN + 1:,}" in msg


def test_long_body_after_first_use_stops_at_the_recorded_size(tmp_path, server):
    server.routes["/toy.hdf5"] = ("body", BODY)
    reg = registry(tmp_path, server.base + "/toy.hdf5", trust="tofu")
    run(tmp_path, reg)
    lock = (tmp_path / "lock.json").read_bytes()
    (tmp_path / "dest" / "d4rl" / "toy-v2.hdf5").unlink()
    server.routes["/toy.hdf5"] = ("chunked", BODY + b"z" * 5000)
    with pytest.raises(SpotError, match=f"the size recorded in the lock file\\); stopped at {PIN + 1:,}"):
        run(tmp_path, reg)
    assert (tmp_path / "lock.json").read_bytes() == lock
    assert not (tmp_path / "dest" / "d4rl" / "toy-v2.hdf5.part").exists()


def test_compressed_body_is_refused(tmp_path, server):
    server.routes["/toy.hdf5"] = ("gzip", BODY)
    msg = refused(tmp_path, registry(tmp_path, server.base + "/toy.hdf5", trust="tofu"))
    assert "Content-Encoding 'gzip'" in msg


def test_the_write_audit_sees_writes(tmp_path):
    """The confinement check is real: it records an open for writing and a rename."""
    (tmp_path / "a").write_text("x")
    os.replace(tmp_path / "a", tmp_path / "b")
    assert str(tmp_path / "a") in _WRITES and str(tmp_path / "b") in _WRITES
