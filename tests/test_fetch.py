"""`spot data fetch` against a real HTTP server on 127.0.0.1 (stdlib http.server in a thread, with
Range support): good file, truncated file, wrong sum, 404, a connection dropped midway, resume of a
partial download, mirror fallback, trust on first use, and the recheck on load. No internet."""

import hashlib
import json
import pickle
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest

from spot import SpotError
from spot.data import fetch
from tests.conftest import run_cli

PT_LABELS = Path(__file__).parent / "data" / "pt-human-labels"


class FileServer:
    """Serves ``files`` (url path -> bytes) with ``Range: bytes=N-`` support and logs every GET.

    ``drop_once``: paths whose first GET announces the full length, sends half and closes.
    ``no_range``: paths served whole (200) whatever the Range header says.
    """

    def __init__(self):
        self.files: dict[str, bytes] = {}
        self.drop_once: set[str] = set()
        self.no_range: set[str] = set()
        self.short_unsized: set[str] = set()  # send no Content-Length and stop 1000 bytes short
        self.log: list[dict] = []
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):
                pass

            def do_GET(self):
                data = server.files.get(self.path)
                rng = self.headers.get("Range")
                entry = {"path": self.path, "range": rng, "status": 404, "sent": 0}
                server.log.append(entry)
                if data is None:
                    self.send_error(404)
                    return
                start = 0
                if rng and self.path not in server.no_range:
                    start = int(rng.removeprefix("bytes=").split("-")[0])
                    if start >= len(data):
                        entry["status"] = 416
                        self.send_response(416)
                        self.send_header("Content-Range", f"bytes */{len(data)}")
                        self.send_header("Content-Length", "0")
                        self.end_headers()
                        return
                    entry["status"] = 206
                    self.send_response(206)
                    self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
                else:
                    entry["status"] = 200
                    self.send_response(200)
                body = data[start:]
                if self.path in server.short_unsized:
                    body = body[:-1000]
                    self.close_connection = True
                else:
                    self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                if self.path in server.drop_once:
                    server.drop_once.discard(self.path)
                    body = body[: len(body) // 2]
                    self.close_connection = True
                entry["sent"] = len(body)  # before writing: the client may check the log once it has the bytes
                self.wfile.write(body)

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.base = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def server(monkeypatch):
    monkeypatch.setenv("NO_PROXY", "127.0.0.1,localhost")
    monkeypatch.setenv("no_proxy", "127.0.0.1,localhost")
    s = FileServer()
    yield s
    s.close()


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def payload(n: int = 300_000, seed: int = 0) -> bytes:
    return np.random.default_rng(seed).bytes(n)


def write_registry(path: Path, files: list[dict], name: str = "d4rl/toy-v2", kind: str = "d4rl") -> Path:
    path.write_text(
        json.dumps({"schema": 1, "sources": {name: {"kind": kind, "description": "test source", "files": files}}})
    )
    return path


def one_file(urls, data=None, trust="third-party", path="d4rl/toy-v2.hdf5", size=True):
    return {
        "path": path,
        "urls": urls,
        "trust": trust,
        "sha256": None if trust == "tofu" else sha(data),
        "size": len(data) if (size and data is not None and trust != "tofu") else None,
    }


def do_fetch(tmp_path, registry, **kw):
    return fetch.fetch(
        "d4rl/toy-v2",
        tmp_path / "dest",
        registry=registry,
        lock=tmp_path / "spot-data.lock.json",
        progress=False,
        backoff=0.0,
        **kw,
    )


def assert_nothing_left(tmp_path):
    """No final file, no partial download, no sidecar in the destination."""
    dest = tmp_path / "dest" / "d4rl"
    left = sorted(p.name for p in dest.iterdir()) if dest.exists() else []
    assert left == [], left


# --------------------------------------------------------------------------- the matrix
def test_good_file_is_verified_renamed_and_not_downloaded_twice(tmp_path, server):
    data = payload()
    server.files["/toy.hdf5"] = data
    reg = write_registry(tmp_path / "reg.json", [one_file([server.base + "/toy.hdf5"], data)])
    result = do_fetch(tmp_path, reg)
    final = tmp_path / "dest" / "d4rl" / "toy-v2.hdf5"
    assert [f.status for f in result.files] == ["downloaded"]
    assert final.read_bytes() == data
    assert not final.with_name(final.name + ".part").exists()
    side = json.loads(fetch.sidecar_path(final).read_text())
    assert side["sha256"] == sha(data) and side["size"] == len(data)
    assert side["url"] == server.base + "/toy.hdf5" and side["trust"] == "third-party"
    assert fetch.verify_fetched(final) is True
    again = do_fetch(tmp_path, reg)
    assert [f.status for f in again.files] == ["present"]
    assert len(server.log) == 1  # the verified file was not fetched again


def test_truncated_file_is_rejected_and_removed(tmp_path, server):
    data = payload()
    server.files["/toy.hdf5"] = data[:200_000]  # the server holds a truncated copy
    reg = write_registry(tmp_path / "reg.json", [one_file([server.base + "/toy.hdf5"], data)])
    with pytest.raises(SpotError) as err:
        do_fetch(tmp_path, reg)
    msg = str(err.value)
    assert server.base + "/toy.hdf5" in msg
    assert "announces 200000 bytes; expected 300000" in msg
    assert_nothing_left(tmp_path)


def test_truncated_file_without_pinned_size_fails_on_the_sum(tmp_path, server):
    data = payload()
    server.files["/toy.hdf5"] = data[:200_000]
    reg = write_registry(tmp_path / "reg.json", [one_file([server.base + "/toy.hdf5"], data, size=False)])
    with pytest.raises(SpotError) as err:
        do_fetch(tmp_path, reg)
    msg = str(err.value)
    assert f"expected {sha(data)}, got {sha(data[:200_000])}" in msg
    assert server.base + "/toy.hdf5" in msg
    assert_nothing_left(tmp_path)


def test_wrong_sum_names_url_expected_and_actual(tmp_path, server):
    data, other = payload(seed=0), payload(seed=1)  # same size, other bytes
    server.files["/toy.hdf5"] = other
    reg = write_registry(tmp_path / "reg.json", [one_file([server.base + "/toy.hdf5"], data)])
    with pytest.raises(SpotError) as err:
        do_fetch(tmp_path, reg)
    msg = str(err.value)
    assert server.base + "/toy.hdf5" in msg
    assert f"expected {sha(data)}, got {sha(other)}" in msg
    assert "third-party" in msg  # says where the expected sum came from
    assert_nothing_left(tmp_path)


def test_404_on_every_url(tmp_path, server):
    data = payload()
    urls = [server.base + "/a.hdf5", server.base + "/b.hdf5"]
    reg = write_registry(tmp_path / "reg.json", [one_file(urls, data)])
    with pytest.raises(SpotError) as err:
        do_fetch(tmp_path, reg)
    msg = str(err.value)
    assert f"{urls[0]}: HTTP 404" in msg and f"{urls[1]}: HTTP 404" in msg
    assert_nothing_left(tmp_path)


def test_dropped_connection_resumes_on_retry(tmp_path, server):
    data = payload()
    server.files["/toy.hdf5"] = data
    server.drop_once.add("/toy.hdf5")
    reg = write_registry(tmp_path / "reg.json", [one_file([server.base + "/toy.hdf5"], data)])
    result = do_fetch(tmp_path, reg)
    assert (tmp_path / "dest" / "d4rl" / "toy-v2.hdf5").read_bytes() == data
    assert result.files[0].status == "downloaded"
    first, second = server.log
    assert first["range"] is None and first["sent"] == len(data) // 2  # then the server hung up
    kept = int(second["range"].removeprefix("bytes=").removesuffix("-"))
    assert 0 < kept <= len(data) // 2  # what was saved before the drop (whole network reads)
    assert second["status"] == 206 and second["sent"] == len(data) - kept  # only the rest


def test_dropped_connection_past_the_retries_keeps_the_partial_file(tmp_path, server):
    data = payload()
    server.files["/toy.hdf5"] = data
    server.drop_once.add("/toy.hdf5")
    reg = write_registry(tmp_path / "reg.json", [one_file([server.base + "/toy.hdf5"], data)])
    with pytest.raises(SpotError, match="connection failed 1 times"):
        do_fetch(tmp_path, reg, retries=0)
    dest = tmp_path / "dest" / "d4rl"
    assert not (dest / "toy-v2.hdf5").exists()
    kept = (dest / "toy-v2.hdf5.part").stat().st_size
    assert 0 < kept <= len(data) // 2  # kept for a resume, never used as the file
    do_fetch(tmp_path, reg)  # a later run resumes it
    assert server.log[-1]["range"] == f"bytes={kept}-" and server.log[-1]["sent"] == len(data) - kept
    assert (dest / "toy-v2.hdf5").read_bytes() == data


def test_resume_of_a_partial_temp_file_requests_only_the_rest(tmp_path, server):
    data = payload()
    server.files["/toy.hdf5"] = data
    part = tmp_path / "dest" / "d4rl" / "toy-v2.hdf5.part"
    part.parent.mkdir(parents=True)
    part.write_bytes(data[:123_456])
    reg = write_registry(tmp_path / "reg.json", [one_file([server.base + "/toy.hdf5"], data)])
    do_fetch(tmp_path, reg)
    assert server.log == [{"path": "/toy.hdf5", "range": "bytes=123456-", "status": 206, "sent": len(data) - 123_456}]
    assert (tmp_path / "dest" / "d4rl" / "toy-v2.hdf5").read_bytes() == data
    assert not part.exists()


def test_server_without_range_support_restarts_the_partial_file(tmp_path, server):
    data = payload()
    server.files["/toy.hdf5"] = data
    server.no_range.add("/toy.hdf5")
    part = tmp_path / "dest" / "d4rl" / "toy-v2.hdf5.part"
    part.parent.mkdir(parents=True)
    part.write_bytes(b"x" * 1000)  # would corrupt the file if appended to
    reg = write_registry(tmp_path / "reg.json", [one_file([server.base + "/toy.hdf5"], data)])
    do_fetch(tmp_path, reg)
    assert server.log[0]["status"] == 200 and server.log[0]["sent"] == len(data)
    assert (tmp_path / "dest" / "d4rl" / "toy-v2.hdf5").read_bytes() == data


def test_mirror_fallback_in_order(tmp_path, server):
    data = payload()
    server.files["/good/toy.hdf5"] = data
    server.files["/bad/toy.hdf5"] = payload(seed=3)
    urls = [server.base + "/missing/toy.hdf5", server.base + "/bad/toy.hdf5", server.base + "/good/toy.hdf5"]
    reg = write_registry(tmp_path / "reg.json", [one_file(urls, data)])
    result = do_fetch(tmp_path, reg)
    assert [e["path"] for e in server.log] == ["/missing/toy.hdf5", "/bad/toy.hdf5", "/good/toy.hdf5"]
    assert result.files[0].url == urls[2]
    assert (tmp_path / "dest" / "d4rl" / "toy-v2.hdf5").read_bytes() == data


def test_user_mirror_is_tried_first_with_the_file_path(tmp_path, server):
    data = payload()
    server.files["/mirror/d4rl/toy-v2.hdf5"] = data
    reg = write_registry(tmp_path / "reg.json", [one_file([server.base + "/origin.hdf5"], data)])
    result = do_fetch(tmp_path, reg, mirrors=[server.base + "/mirror/"])
    assert [e["path"] for e in server.log] == ["/mirror/d4rl/toy-v2.hdf5"]
    assert result.files[0].url == server.base + "/mirror/d4rl/toy-v2.hdf5"


def test_tofu_resume_that_ends_short_of_the_announced_size_is_rejected(tmp_path, server):
    """No pinned size or sum yet: a transfer that ends cleanly before the size the server's
    Content-Range announced is still caught, and nothing is recorded in the lock."""
    data = payload()
    server.files["/toy.hdf5"] = data
    server.short_unsized.add("/toy.hdf5")
    part = tmp_path / "dest" / "d4rl" / "toy-v2.hdf5.part"
    part.parent.mkdir(parents=True)
    part.write_bytes(data[:1000])
    reg = write_registry(tmp_path / "reg.json", [one_file([server.base + "/toy.hdf5"], trust="tofu")])
    with pytest.raises(SpotError, match=f"got {len(data) - 1000} bytes; the server announced {len(data)}"):
        do_fetch(tmp_path, reg)
    assert server.log[0]["range"] == "bytes=1000-" and server.log[0]["status"] == 206
    assert_nothing_left(tmp_path)
    assert not (tmp_path / "spot-data.lock.json").exists()


# --------------------------------------------------------------------------- trust on first use
def test_tofu_records_the_first_download_and_holds_later_ones_to_it(tmp_path, server):
    data = payload()
    server.files["/toy.hdf5"] = data
    reg = write_registry(tmp_path / "reg.json", [one_file([server.base + "/toy.hdf5"], trust="tofu")])
    result = do_fetch(tmp_path, reg)
    assert result.files[0].status == "recorded"
    lock = json.loads((tmp_path / "spot-data.lock.json").read_text())
    rec = lock["files"]["d4rl/toy-v2:d4rl/toy-v2.hdf5"]
    assert rec["sha256"] == sha(data) and rec["size"] == len(data) and rec["trust"] == "tofu"
    assert "Trust-on-first-use" in lock["about"] and "Commit this file" in lock["about"]

    # The file on the server changes: a fresh download is held to the recorded sum.
    changed = payload(seed=9)
    server.files["/toy.hdf5"] = changed
    (tmp_path / "dest" / "d4rl" / "toy-v2.hdf5").unlink()
    with pytest.raises(SpotError) as err:
        do_fetch(tmp_path, reg)
    msg = str(err.value)
    assert f"expected {sha(data)}, got {sha(changed)}" in msg and "lock file" in msg
    left = sorted(p.name for p in (tmp_path / "dest" / "d4rl").iterdir())
    assert "toy-v2.hdf5" not in left and "toy-v2.hdf5.part" not in left


# --------------------------------------------------------------------------- recheck on load
def test_loader_rechecks_a_fetched_dataset_file(tmp_path, server):
    from spot.data import formats, registry
    from spot.data.dataset import RawDataset
    from tests.conftest import make_dataset

    ds = make_dataset([30, 20])
    src = tmp_path / "toy.hdf5"
    raw = RawDataset(
        observations=ds.observations,
        actions=ds.actions,
        rewards=ds.rewards,
        terminals=ds.terminals,
        timeouts=np.r_[np.zeros(29, bool), True, np.zeros(19, bool), True],
        next_observations=ds.next_observations,
    )
    formats.write_d4rl_hdf5(raw, src)
    data = src.read_bytes()
    server.files["/toy.hdf5"] = data
    reg = write_registry(tmp_path / "reg.json", [one_file([server.base + "/toy.hdf5"], data)])
    final = do_fetch(tmp_path, reg).files[0].path
    loaded, card = registry.load(str(final))
    assert len(loaded) == 48 and card["source"] == "file"  # the fetched file reads as D4RL hdf5

    blob = bytearray(final.read_bytes())
    blob[-1] ^= 0xFF  # a byte flips on disk after the verified download
    final.write_bytes(bytes(blob))
    with pytest.raises(SpotError, match="changed since it was verified") as err:
        registry.load(str(final))
    assert sha(data) in str(err.value) and sha(bytes(blob)) in str(err.value)


def test_packaged_pt_label_sums_match_the_real_files_and_load(tmp_path, server):
    """The packaged registry's PT label pins equal the real files (tests/data copies of PT's
    human_label/); fetched through --mirror from the local server, they load with read_pt_labels."""
    from spot.data import labels

    sources = fetch.load_registry()
    for name in ("pt-labels/hopper-medium-replay-v2", "pt-labels/Lift_ph"):
        for f in sources[name].files:
            data = (PT_LABELS / Path(f.path).relative_to("pt-labels")).read_bytes()
            assert (f.sha256, f.size, f.trust) == (sha(data), len(data), "git-commit")
            server.files["/m/" + f.path] = data
    result = fetch.fetch(
        "pt-labels/hopper-medium-replay-v2",
        tmp_path / "dest",
        mirrors=[server.base + "/m"],
        lock=tmp_path / "lock.json",
        progress=False,
    )
    folder = result.files[0].path.parent
    prefs = labels.read_pt_labels(folder)
    assert len(prefs) == 500 and prefs.segment_length == 100
    assert len(server.log) == 3 and all(e["path"].startswith("/m/pt-labels/") for e in server.log)

    label = folder / "label_human"
    label.write_bytes(pickle.dumps([0] * 500))  # replaced on disk: not the verified file
    with pytest.raises(SpotError, match="label_human' changed since it was verified"):
        labels.read_pt_labels(folder)


# --------------------------------------------------------------------------- registry
def test_packaged_registry_covers_the_paper_data():
    sources = fetch.load_registry()
    for env in ("hopper", "walker2d"):
        for kind in ("random", "medium", "expert", "medium-replay", "medium-expert", "full-replay"):
            assert f"d4rl/{env}-{kind}-v2" in sources
    for task in ("lift-ph", "lift-mh", "can-ph", "can-mh"):
        assert f"robomimic/{task}" in sources and sources[f"robomimic/{task}"].labels in sources
    d4rl = sources["d4rl/hopper-medium-expert-v2"].files[0]
    assert d4rl.trust == "lfs-oid" and len(d4rl.urls) == 2 and d4rl.path.endswith(".hdf5")
    assert fetch.resolve("hopper-medium-replay-v2", sources).name == "d4rl/hopper-medium-replay-v2"
    assert fetch.resolve("Lift_ph", sources).name == "pt-labels/Lift_ph"


@pytest.mark.parametrize(
    "bad, key",
    [
        ({"trust": "tofu", "sha256": "0" * 64}, "no pinned 'sha256'"),
        ({"trust": "lfs-oid", "sha256": "xyz"}, "64 lowercase hex"),
        ({"trust": "sure"}, "'trust' is 'sure'"),
        ({"urls": ["ftp://x/y"]}, "http(s) URLs"),
        ({"path": "../escape.hdf5"}, "relative path"),
    ],
)
def test_bad_registry_entries_name_the_key(tmp_path, bad, key):
    entry = {
        "path": "d4rl/x.hdf5",
        "urls": ["http://127.0.0.1:9/x"],
        "trust": "lfs-oid",
        "sha256": "a" * 64,
        "size": 3,
        **bad,
    }
    reg = write_registry(tmp_path / "reg.json", [entry])
    with pytest.raises(SpotError, match="source 'd4rl/toy-v2', files\\[0\\]") as err:
        fetch.load_registry(reg)
    assert key in str(err.value)


def test_unknown_name_suggests_close_ones():
    with pytest.raises(SpotError, match="did you mean d4rl/hopper-medium-replay-v2"):
        fetch.resolve("hoper-medium-replay-v2", fetch.load_registry())


# --------------------------------------------------------------------------- Minari backend
def test_minari_missing_is_a_clear_error(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "minari", None)
    with pytest.raises(SpotError, match=r"optional 'minari' extra: pip install 'spot-pbrl\[minari\]'"):
        fetch.fetch_minari("mujoco/hopper/medium-v0", lock=tmp_path / "lock.json")


def test_minari_bad_dataset_id_is_a_clear_error(tmp_path):
    pytest.importorskip("minari")
    with pytest.raises(SpotError, match="Minari could not download 'not a dataset id!'"):
        fetch.fetch_minari("not a dataset id!", lock=tmp_path / "lock.json")
    assert not (tmp_path / "lock.json").exists()


# --------------------------------------------------------------------------- CLI
def test_cli_fetch_list_and_fetch_through_a_registry_file(tmp_path, server):
    listed = run_cli("data", "fetch", "--list")
    assert listed.returncode == 0, listed.stderr
    assert "d4rl/hopper-medium-replay-v2" in listed.stdout and "robomimic/can-mh" in listed.stdout
    assert "tofu" in listed.stdout and "minari:<dataset id>" in listed.stdout

    data = payload()
    server.files["/toy.hdf5"] = data
    reg = write_registry(tmp_path / "reg.json", [one_file([server.base + "/toy.hdf5"], trust="tofu")])
    env = {"NO_PROXY": "127.0.0.1", "no_proxy": "127.0.0.1"}
    args = (
        "data",
        "fetch",
        "toy-v2",
        "--registry",
        str(reg),
        "--dest",
        str(tmp_path / "d"),
        "--lock",
        str(tmp_path / "l.json"),
        "--quiet",
    )
    out = run_cli(*args, env=env)
    assert out.returncode == 0, out.stderr
    assert "recorded" in out.stdout and "TOFU" in out.stdout and sha(data) in out.stdout
    assert "data.name=" + str(tmp_path / "d" / "d4rl" / "toy-v2.hdf5") in out.stdout

    server.files["/toy.hdf5"] = payload(seed=5)
    (tmp_path / "d" / "d4rl" / "toy-v2.hdf5").unlink()
    bad = run_cli(*args, env=env)
    assert bad.returncode == 2
    assert bad.stderr.startswith("error: could not fetch 'd4rl/toy-v2.hdf5'") and sha(data) in bad.stderr
