"""Tests of downloading and unpacking TUM archives (atlas_pipeline.sensors.download) against a
local HTTP server on 127.0.0.1 (no network needed)."""

from __future__ import annotations

import functools
import hashlib
import http.server
import io
import tarfile
import threading
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from atlas_pipeline.errors import DatasetError
from atlas_pipeline.sensors.camera import TUM_CAMERAS
from atlas_pipeline.sensors.download import download_tum_archive
from atlas_pipeline.sensors.registry import DatasetEntry, ensure_dataset_files

TOP = "rgbd_dataset_test"
MAX_REQUESTS = 20  # the whole module makes a handful; more means a retry loop gone wrong


# ---- a tiny TUM-layout archive ------------------------------------------------------------------


def _png_bytes(img: np.ndarray) -> bytes:
    return iio.imwrite("<bytes>", img, extension=".png")


def _sequence_files() -> dict[str, bytes]:
    """Relative path -> content of a 2-frame TUM sequence with 8x6 images."""
    rng = np.random.default_rng(0)
    files: dict[str, bytes] = {}
    rgb_rows, depth_rows = [], []
    gt_rows = []
    for i in range(2):
        t = 1305031102.0 + 0.1 * i
        rgb = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
        depth = np.full((6, 8), 5000 + 100 * i, dtype=np.uint16)  # 1.0 m, 1.02 m at scale 5000
        files[f"rgb/{t:.6f}.png"] = _png_bytes(rgb)
        files[f"depth/{t + 0.01:.6f}.png"] = _png_bytes(depth)
        rgb_rows.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_rows.append(f"{t + 0.01:.6f} depth/{t + 0.01:.6f}.png")
        gt_rows.append(f"{t:.4f} {0.01 * i:.4f} 0.0000 0.0000 0.0000 0.0000 0.0000 1.0000")
    files["rgb.txt"] = ("# color images\n# timestamp filename\n" + "\n".join(rgb_rows) + "\n").encode()
    files["depth.txt"] = ("# depth maps\n# timestamp filename\n" + "\n".join(depth_rows) + "\n").encode()
    files["groundtruth.txt"] = ("# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n"
                                + "\n".join(gt_rows) + "\n").encode()
    return files


def _add_bytes(tar: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    info.size = len(data)
    info.mode = 0o644
    tar.addfile(info, io.BytesIO(data))


def make_tgz(path: Path, extra: dict[str, bytes] | None = None,
             special: list[tarfile.TarInfo] | None = None) -> Path:
    """Write ``path`` (.tgz): ``rgbd_dataset_test/`` with the sequence, plus ``extra`` members
    (names taken literally, e.g. ``../evil.txt``) and ``special`` data-less members (links, fifos)."""
    with tarfile.open(path, "w:gz") as tar:
        for d in (TOP, f"{TOP}/rgb", f"{TOP}/depth"):
            info = tarfile.TarInfo(d)
            info.type = tarfile.DIRTYPE
            info.mode = 0o755
            tar.addfile(info)
        for rel, data in _sequence_files().items():
            _add_bytes(tar, f"{TOP}/{rel}", data)
        for name, data in (extra or {}).items():
            _add_bytes(tar, name, data)
        for info in special or []:
            tar.addfile(info)
    return path


def _special_member(name: str, kind: bytes, linkname: str = "") -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type = kind
    info.linkname = linkname
    info.mode = 0o644
    return info


def sha256_of(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def all_files(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()}


# ---- local HTTP server ---------------------------------------------------------------------------


class _Server:
    def __init__(self, root: Path, httpd: http.server.ThreadingHTTPServer, counter: list[str]):
        self.root = root
        self.httpd = httpd
        self.requests = counter

    def url(self, name: str) -> str:
        host, port = self.httpd.server_address[:2]
        return f"http://{host}:{port}/{name}"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """A static file server on 127.0.0.1 (ephemeral port) serving a temporary folder."""
    root = tmp_path_factory.mktemp("www")
    seen: list[str] = []

    class Handler(http.server.SimpleHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 - http.server naming
            seen.append(self.path)
            if len(seen) > MAX_REQUESTS:
                self.send_error(429, "too many requests in this test module")
                return
            if self.path.startswith("/truncated/"):
                # announces more bytes than it sends, then closes the connection
                data = (root / self.path.split("/")[-1]).read_bytes()
                self.send_response(200)
                self.send_header("Content-Type", "application/gzip")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data[: len(data) // 2])
                self.close_connection = True
                return
            if self.path.startswith("/chunked-drop/"):
                # chunked transfer encoding, connection dropped in the middle of a chunk
                data = (root / self.path.split("/")[-1]).read_bytes()
                self.protocol_version = "HTTP/1.1"
                self.send_response(200)
                self.send_header("Content-Type", "application/gzip")
                self.send_header("Transfer-Encoding", "chunked")
                self.send_header("Connection", "close")
                self.end_headers()
                self.wfile.write(f"{len(data):x}\r\n".encode() + data[: len(data) // 2])
                self.wfile.flush()
                self.close_connection = True
                return
            super().do_GET()

        def log_message(self, *args):  # keep pytest output clean
            pass

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Handler, directory=str(root)))
    httpd.daemon_threads = True
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    srv = _Server(root, httpd, seen)
    try:
        yield srv
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join(timeout=5)
    assert len(seen) <= MAX_REQUESTS, f"{len(seen)} requests: {seen}"


@pytest.fixture(scope="module")
def good_archive(server) -> Path:
    return make_tgz(server.root / "good.tgz")


# ---- tests ---------------------------------------------------------------------------------------


def test_download_unpacks_tum_layout(server, good_archive, tmp_path):
    dest = tmp_path / "data" / "seq"
    n0 = len(server.requests)
    logs: list[str] = []
    out = download_tum_archive(server.url("good.tgz"), dest, sha256=sha256_of(good_archive), log=logs.append)
    assert out == dest
    assert len(server.requests) - n0 == 1
    expected = set(_sequence_files())
    assert all_files(dest) == expected  # the top folder's content, not the top folder itself
    for rel, data in _sequence_files().items():
        assert (dest / rel).read_bytes() == data
    rgb = iio.imread(next((dest / "rgb").iterdir()))
    depth = iio.imread(next((dest / "depth").iterdir()))
    assert rgb.shape == (6, 8, 3) and rgb.dtype == np.uint8
    assert depth.shape == (6, 8) and depth.dtype == np.uint16 and depth.min() >= 5000
    # nothing left beside the destination: no temporary folder, no archive, no .part file
    assert sorted(p.name for p in dest.parent.iterdir()) == ["seq"]
    assert any("unpacked" in m for m in logs)


def test_download_without_checksum_and_replaces_nothing_else(server, good_archive, tmp_path):
    (tmp_path / "keep.txt").write_text("x")
    dest = tmp_path / "seq"
    download_tum_archive(server.url("good.tgz"), dest, log=lambda m: None)
    assert (dest / "rgb.txt").is_file() and (dest / "depth.txt").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt", "seq"]


def test_wrong_sha256_raises_and_leaves_no_destination(server, good_archive, tmp_path):
    dest = tmp_path / "seq"
    with pytest.raises(DatasetError, match="checksum mismatch"):
        download_tum_archive(server.url("good.tgz"), dest, sha256="0" * 64, log=lambda m: None)
    assert not dest.exists()
    assert list(tmp_path.iterdir()) == []  # temporary folder and partial download removed


@pytest.mark.parametrize("evil", ["../evil.txt", f"{TOP}/../../evil.txt"], ids=["dotdot", "nested-dotdot"])
def test_archive_with_member_outside_is_refused(server, tmp_path, evil):
    name = f"evil-{evil.count('..')}.tgz"
    make_tgz(server.root / name, extra={evil: b"pwned\n"})
    base = tmp_path / "a" / "b"  # room above the destination to see an escape
    dest = base / "seq"
    with pytest.raises(DatasetError, match="cannot unpack") as exc_info:
        download_tum_archive(server.url(name), dest, log=lambda m: None)
    assert server.url(name) in str(exc_info.value)
    assert not dest.exists()
    assert list(base.iterdir()) == []  # temporary folder removed
    assert not any(p.name == "evil.txt" for p in tmp_path.rglob("*"))


def test_http_404_names_the_url(server, tmp_path):
    url = server.url("no-such-archive.tgz")
    dest = tmp_path / "seq"
    with pytest.raises(DatasetError) as exc_info:
        download_tum_archive(url, dest, log=lambda m: None)
    assert url in str(exc_info.value)
    assert "404" in str(exc_info.value)
    assert not dest.exists()
    assert list(tmp_path.iterdir()) == []


def test_archive_without_tum_layout_is_refused(server, tmp_path):
    path = server.root / "notum.tgz"
    with tarfile.open(path, "w:gz") as tar:
        _add_bytes(tar, "something/readme.txt", b"not a dataset\n")
    dest = tmp_path / "seq"
    with pytest.raises(DatasetError, match="rgb.txt"):
        download_tum_archive(server.url("notum.tgz"), dest, log=lambda m: None)
    assert not dest.exists()
    assert list(tmp_path.iterdir()) == []


def test_truncated_download_is_refused(server, good_archive, tmp_path):
    url = server.url("truncated/good.tgz")
    dest = tmp_path / "seq"
    with pytest.raises(DatasetError, match="truncated") as exc_info:
        download_tum_archive(url, dest, log=lambda m: None)
    assert url in str(exc_info.value)
    assert not dest.exists()
    assert list(tmp_path.iterdir()) == []


def test_connection_dropped_mid_chunked_download_raises_dataset_error(server, good_archive, tmp_path):
    url = server.url("chunked-drop/good.tgz")
    dest = tmp_path / "seq"
    try:
        download_tum_archive(url, dest, log=lambda m: None)
    except DatasetError as exc:
        assert url in str(exc)
    except Exception as exc:  # noqa: BLE001 - the point of the test
        raise AssertionError(f"expected DatasetError, got {type(exc).__module__}.{type(exc).__name__}: {exc}")
    else:
        raise AssertionError("a cut-off download was accepted")
    finally:
        assert not dest.exists()
        assert list(tmp_path.iterdir()) == []


def test_body_that_is_not_an_archive_is_refused(server, tmp_path):
    (server.root / "page.tgz").write_text("<html>Moved</html>\n")
    url = server.url("page.tgz")
    dest = tmp_path / "seq"
    with pytest.raises(DatasetError, match="cannot unpack") as exc_info:
        download_tum_archive(url, dest, log=lambda m: None)
    assert url in str(exc_info.value)
    assert not dest.exists()
    assert list(tmp_path.iterdir()) == []


def test_empty_archive_is_refused(server, tmp_path):
    with tarfile.open(server.root / "empty.tgz", "w:gz"):
        pass
    dest = tmp_path / "seq"
    with pytest.raises(DatasetError):
        download_tum_archive(server.url("empty.tgz"), dest, log=lambda m: None)
    assert not dest.exists()


def test_ensure_dataset_files_downloads_missing_folder(server, good_archive, tmp_path):
    dest = tmp_path / "datasets" / "missing"
    entry = DatasetEntry(name="tum-test", kind="tum", path=dest, url=server.url("good.tgz"),
                         sha256=sha256_of(good_archive), camera=TUM_CAMERAS["default"])
    logs: list[str] = []
    n0 = len(server.requests)
    assert ensure_dataset_files(entry, logs.append) == dest
    assert all_files(dest) == set(_sequence_files())
    assert any("downloading" in m and entry.url in m for m in logs)
    # second call: the folder exists, nothing is downloaded again
    assert ensure_dataset_files(entry, logs.append) == dest
    assert len(server.requests) - n0 == 1


def test_ensure_dataset_files_without_url_raises(tmp_path):
    entry = DatasetEntry(name="tum-test", kind="tum", path=tmp_path / "missing", camera=TUM_CAMERAS["default"])
    with pytest.raises(DatasetError, match="no url"):
        ensure_dataset_files(entry)


# ---- members the unpacker validates itself (not relying on tarfile's "data" filter) -------------


def _assert_refused_untouched(server, name: str, tmp_path: Path, member: str, why: str) -> None:
    """Download ``name``: a DatasetError naming the URL, the member and ``why``; nothing written."""
    base = tmp_path / "a" / "b"
    dest = base / "seq"
    with pytest.raises(DatasetError, match="cannot unpack") as exc_info:
        download_tum_archive(server.url(name), dest, log=lambda m: None)
    msg = str(exc_info.value)
    assert server.url(name) in msg and repr(member) in msg and why in msg, msg
    assert not dest.exists()
    assert list(base.iterdir()) == []  # temporary folder removed
    assert not any(p.name in ("evil.txt", "passwd", "link") for p in tmp_path.rglob("*"))


@pytest.mark.parametrize("kind, linkname", [(tarfile.SYMTYPE, "/etc/passwd"), (tarfile.SYMTYPE, "../../.."),
                                            (tarfile.LNKTYPE, f"{TOP}/rgb.txt")],
                         ids=["symlink-absolute", "symlink-up", "hardlink"])
def test_archive_with_link_member_is_refused(server, tmp_path, kind, linkname):
    member = f"{TOP}/link"
    name = f"link-{ord(kind)}-{linkname.count('.')}.tgz"
    make_tgz(server.root / name, special=[_special_member(member, kind, linkname)])
    _assert_refused_untouched(server, name, tmp_path, member, "is a link")


def test_archive_with_fifo_member_is_refused(server, tmp_path):
    member = f"{TOP}/fifo"
    make_tgz(server.root / "fifo.tgz", special=[_special_member(member, tarfile.FIFOTYPE)])
    _assert_refused_untouched(server, "fifo.tgz", tmp_path, member, "not a regular file or folder")


def test_archive_with_absolute_member_is_refused(server, tmp_path):
    member = "/tmp/evil.txt"
    make_tgz(server.root / "absolute.tgz", extra={member: b"pwned\n"})
    _assert_refused_untouched(server, "absolute.tgz", tmp_path, member, "absolute path")


def test_archive_with_dotdot_member_names_it(server, tmp_path):
    member = f"{TOP}/rgb/../../evil.txt"
    make_tgz(server.root / "dotdot-named.tgz", extra={member: b"pwned\n"})
    _assert_refused_untouched(server, "dotdot-named.tgz", tmp_path, member, "'..' component")


def test_non_empty_destination_is_never_replaced(server, good_archive, tmp_path):
    dest = tmp_path / "seq"
    dest.mkdir()
    (dest / "my_recording.txt").write_text("precious\n")
    n0 = len(server.requests)
    with pytest.raises(DatasetError, match="will not overwrite") as exc_info:
        download_tum_archive(server.url("good.tgz"), dest, log=lambda m: None)
    assert str(dest) in str(exc_info.value)
    assert len(server.requests) == n0  # refused before downloading anything
    assert all_files(dest) == {"my_recording.txt"} and (dest / "my_recording.txt").read_text() == "precious\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]


def test_existing_file_as_destination_is_refused(tmp_path):
    dest = tmp_path / "seq"
    dest.write_text("not a folder\n")
    with pytest.raises(DatasetError, match="will not overwrite"):
        download_tum_archive("http://127.0.0.1:9/never-fetched.tgz", dest, log=lambda m: None)
    assert dest.read_text() == "not a folder\n"


def test_empty_existing_destination_is_filled(server, good_archive, tmp_path):
    dest = tmp_path / "seq"
    dest.mkdir()
    download_tum_archive(server.url("good.tgz"), dest, sha256=sha256_of(good_archive), log=lambda m: None)
    assert all_files(dest) == set(_sequence_files())
