"""``stsdic view`` without a browser: what the server answers (values checked against the
HDF5 file), what it refuses (paths outside its routes, other hosts), the drawn region's
mask and run command, and the command line (free port printed, Ctrl-C ends it cleanly)."""

from __future__ import annotations

import http.client
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from view_support import FAST, RUN, make_result, serving, serving_result, writing

from torch_stsdic.cli import main
from torch_stsdic.core.status import usable
from torch_stsdic.io import load_series, read_mask
from torch_stsdic.plot import colour_norm
from torch_stsdic.view.region import Region, rasterise, run_command
from torch_stsdic.view.server import draw_api
from torch_stsdic.view.source import ImageSource, ResultSource

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def result(tmp_path_factory) -> tuple[Path, Path]:
    return make_result(tmp_path_factory.mktemp("view"))


def _get(server, path: str, host: str | None = None, method: str = "GET", body=None,
         headers=None) -> tuple[int, bytes, dict]:
    """A raw request (the path sent exactly as given)."""
    port = server.server_address[1]
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
    conn.putheader("Host", host or f"127.0.0.1:{port}")
    for k, v in (headers or {}).items():
        conn.putheader(k, v)
    if body is not None:
        conn.putheader("Content-Length", str(len(body)))
    conn.endheaders(body)
    r = conn.getresponse()
    data = r.read()
    conn.close()
    return r.status, data, dict(r.getheaders())


def _json(server, path: str):
    status, data, _ = _get(server, path)
    assert status == 200, data
    return json.loads(data)


# ----------------------------------------------------------------------------------------
# the data: the same numbers as the file
# ----------------------------------------------------------------------------------------


def test_field_point_history_and_limits_are_the_files(result):
    movie, path = result
    with h5py.File(path, "r") as f:
        u, status, zncc, u_std = (f[k][()] for k in ("u", "status", "zncc", "u_std"))
        points = f["points"][()]
    valid = usable(status) & (np.nan_to_num(zncc, nan=-1) >= 0.8)
    with serving_result(path) as server:
        meta = _json(server, "/api/meta")
        assert meta["kind"] == "2d" and meta["n_points"] == len(points) and meta["n_rows"] == 7
        assert np.allclose(np.reshape(meta["points"], (-1, 2)), points)
        assert meta["image"] == {"width": 120, "height": 100, "frames": 7}
        assert {f["name"] for f in meta["fields"]} >= {"u", "v", "ut", "exx", "u_std", "zncc"}
        for row in (0, 3, 6):
            status_code, data, hdr = _get(server, f"/api/field?name=u&row={row}")
            assert status_code == 200 and hdr["Content-Type"] == "application/octet-stream"
            got = np.frombuffer(data, "<f4")
            want = np.where(valid[row], u[row], np.nan).astype(np.float32)
            np.testing.assert_array_equal(got, want)
        k = len(points) // 2
        p = _json(server, f"/api/point?row=4&point={k}")
        assert p["values"]["u"] == pytest.approx(float(u[4, k]))
        assert p["values"]["status"] == int(status[4, k])
        assert (p["x"], p["y"]) == (points[k, 0], points[k, 1])
        h = _json(server, f"/api/history?point={k}&name=u")
        assert np.allclose(np.array(h["values"], dtype=float), np.where(valid[:, k], u[:, k],
                                                                         np.nan), equal_nan=True)
        assert np.allclose(np.array(h["std"], dtype=float),
                           np.where(valid[:, k], u_std[:, k], np.nan), equal_nan=True)
        lim = _json(server, "/api/limits?name=u")
        norm = colour_norm(np.where(valid, u, np.nan), None, None, False)
        assert (lim["lo"], lim["hi"]) == pytest.approx((norm.vmin, norm.vmax))
        assert lim["cmap"] == "viridis" and lim["label"] == "u (px)"
        status_code, data, hdr = _get(server, "/api/image?frame=2")
        assert status_code == 200 and data[:8] == b"\x89PNG\r\n\x1a\n"
        pos = np.frombuffer(_get(server, "/api/positions?row=5")[1], "<f4").reshape(-1, 2)
        moved = points + np.nan_to_num(np.stack([u[5], f_v(path)[5]], 1))
        np.testing.assert_allclose(pos, moved, atol=1e-4)


def f_v(path: Path) -> np.ndarray:
    with h5py.File(path, "r") as f:
        return f["v"][()]


def test_calibrated_file_is_shown_in_its_units(result, tmp_path):
    _, path = result
    cal = tmp_path / "mm.h5"
    cal.write_bytes(path.read_bytes())
    with h5py.File(cal, "r+") as f:
        f.attrs["scale"], f.attrs["unit"] = 0.02, "mm"
        u = f["u"][()]
    src = ResultSource(cal)
    vals = src.row_values("u", 3, -1.0)
    finite = np.isfinite(vals)
    np.testing.assert_allclose(vals[finite], 0.02 * u[3][finite], rtol=1e-6)
    assert src.label("u") == "u (mm)" and src.label("ut") == "ut (mm/frame)"
    assert src.label("exx") == "exx (-)"


def test_bad_questions_get_400_with_one_line(result):
    _, path = result
    with serving_result(path) as server:
        for q in ("/api/field?name=nope&row=0", "/api/field?name=u&row=99",
                  "/api/field?name=u&row=x", "/api/point?row=0&point=-1",
                  "/api/history?point=0", "/api/image?frame=700",
                  "/api/field?name=u&row=0&min_zncc=nan"):
            status, data, _ = _get(server, q)
            assert status == 400, q
            assert "\n" not in json.loads(data)["error"]


def test_a_file_still_being_written_shows_its_finished_rows(tmp_path):
    path = tmp_path / "live.h5"
    with writing(path) as run, serving_result(path) as server:
        assert _json(server, "/api/progress")["completed"] == "110000"
        got = np.frombuffer(_get(server, "/api/field?name=u&row=3")[1], "<f4")
        assert np.isnan(got).all()  # not finished: nothing shown
        run.more(2)
        assert _json(server, "/api/progress")["completed"] == "111100"
        got = np.frombuffer(_get(server, "/api/field?name=u&row=3")[1], "<f4")
        pts = np.reshape(_json(server, "/api/meta")["points"], (-1, 2))
        np.testing.assert_allclose(got, 3 * (1 + pts[:, 0] / 100), rtol=1e-6)


# ----------------------------------------------------------------------------------------
# safety: only its own routes, only to itself
# ----------------------------------------------------------------------------------------

OUTSIDE = [
    "/../pyproject.toml", "/assets/../../pyproject.toml", "/assets/../view/source.py",
    "/assets/%2e%2e/%2e%2e/pyproject.toml", "/assets/..%2f..%2fpyproject.toml",
    "/%2e%2e/%2e%2e/%2e%2e/etc/passwd", "/etc/passwd", "//etc/passwd", "/assets//etc/passwd",
    "/assets/%2Fetc%2Fpasswd", "/assets/view.js/../../../../etc/passwd",
    "/api/../assets/view.js", "/assets/VIEW.JS", "/assets/view.js%00.py",
    "/torch_stsdic/view/source.py", "/api/image?frame=../../../../etc/passwd",
]


@pytest.mark.parametrize("target", OUTSIDE)
def test_requests_outside_the_served_files_are_refused(result, target):
    _, path = result
    secret = (ROOT / "pyproject.toml").read_bytes()[:40]
    with serving_result(path) as server:
        status, data, _ = _get(server, target)
    assert status in (400, 404), (target, status)
    assert secret not in data and b"root:" not in data


def test_the_drawing_page_refuses_them_too(result, tmp_path):
    movie, _ = result
    secret = (ROOT / "pyproject.toml").read_bytes()[:40]
    get, post = draw_api(ImageSource(load_series(str(movie))), 0, [str(movie)],
                         tmp_path / "m.png")
    with serving(get, post) as server:
        for target in OUTSIDE:
            status, data, _ = _get(server, target)
            assert status in (400, 404) and secret not in data, target
            status, data, _ = _get(server, target, method="POST", body=b"{}",
                                   headers={"Content-Type": "application/json"})
            assert status in (400, 404) and secret not in data, target
        assert _get(server, "/api/region", method="POST", body=b"{}", host="evil.example:1",
                    headers={"Content-Type": "application/json"})[0] == 403
        assert _get(server, "/api/region", method="POST", body=b"roi",
                    headers={"Content-Type": "text/plain"})[0] == 415
    assert not (tmp_path / "m.png").exists()


def test_absolute_form_and_other_hosts_are_refused(result):
    _, path = result
    with serving_result(path) as server:
        port = server.server_address[1]
        assert server.server_address[0] == "127.0.0.1"
        assert _get(server, f"http://127.0.0.1:{port}/etc/passwd")[0] == 404
        assert _get(server, f"http://127.0.0.1:{port}/")[0] == 404  # absolute form: not served
        assert _get(server, "/", host="evil.example:80")[0] == 403  # DNS rebinding
        assert _get(server, "/api/meta", host=f"evil.example:{port}")[0] == 403
        assert _get(server, "/", host=f"localhost:{port}")[0] == 200
        status, data, hdr = _get(server, "/")
        assert status == 200 and b"stsdic view" in data
        assert "default-src 'self'" in hdr["Content-Security-Policy"]
        assert _get(server, "/assets/view.js")[0] == 200
        # no writes on a result page, and none from another origin anywhere
        assert _get(server, "/api/region", method="POST", body=b"{}",
                    headers={"Content-Type": "application/json"})[0] == 404


def test_every_asset_the_page_names_is_served(result):
    """The page works offline: every file it loads comes from the package."""
    import re

    from torch_stsdic.view.server import ASSETS

    _, path = result
    with serving_result(path) as server:
        page = _get(server, "/")[1].decode()
        names = re.findall(r'(?:src|href)="([^"]+)"', page)
        assert names and all(n.startswith("/assets/") or n.startswith("data:") for n in names)
        for n in names:
            if n.startswith("/assets/"):
                assert n[len("/assets/"):] in ASSETS and _get(server, n)[0] == 200
        for name in ASSETS:
            body = _get(server, f"/assets/{name}")[1].decode()
            assert "http://" not in body and "https://" not in body  # no CDN


# ----------------------------------------------------------------------------------------
# the drawn region
# ----------------------------------------------------------------------------------------


def _hand_mask(shape) -> np.ndarray:
    """The region of :data:`DRAWN` typed by hand: a rectangle with a rectangular hole,
    outlines included in the region and left out with the hole."""
    m = np.zeros(shape, dtype=bool)
    m[22:79, 15:101] = True
    m[40:56, 40:71] = False
    return m


#: a region polygon and a hole, as the page sends them
DRAWN = {"roi": [12, 18, 106, 84], "polygons": [
    {"kind": "region", "points": [[15, 22], [100, 22], [100, 78], [15, 78]]},
    {"kind": "hole", "points": [[40, 40], [70, 40], [70, 55], [40, 55]]}]}


def test_rasterise_follows_the_documented_rule():
    reg = Region.from_json(DRAWN, (100, 120))
    assert reg.roi == (12, 18, 106, 84)
    np.testing.assert_array_equal(rasterise(reg, (100, 120)), _hand_mask((100, 120)))
    only_hole = Region.from_json({"polygons": [DRAWN["polygons"][1]]}, (100, 120))
    m = rasterise(only_hole, (100, 120))
    assert m.sum() == 100 * 120 - 31 * 16 and not m[40:56, 40:71].any()
    tri = Region.from_json({"polygons": [{"kind": "region", "points": [[0, 0], [10, 0],
                                                                         [0, 10]]}]}, (20, 20))
    yy, xx = np.mgrid[:20, :20]
    np.testing.assert_array_equal(rasterise(tri, (20, 20)), xx + yy <= 10)


@pytest.mark.parametrize("bad", [
    [], {"roi": [1, 2, 3]}, {"roi": [5, 5, 5, 9]}, {"polygons": [{"kind": "x", "points": []}]},
    {"polygons": [{"kind": "hole", "points": [[1, 2], [3, 4]]}]},
    {"polygons": [{"kind": "hole", "points": [[1, 2], [3, "a"], [5, 6]]}]},
    {"polygons": "no"}])
def test_malformed_regions_are_refused(bad):
    with pytest.raises(ValueError):
        Region.from_json(bad, (100, 120))


def test_run_command_quotes_its_words():
    assert run_command(["a b.tif"], (1, 2, 3, 4), "m.png") == \
        "stsdic run 'a b.tif' --roi 1 2 3 4 --mask m.png --out result.h5"
    assert run_command(["x.tif"], None, None) == "stsdic run x.tif --out result.h5"


def test_saved_region_gives_the_run_of_the_same_roi_and_mask_typed_by_hand(result, tmp_path):
    movie, _ = result
    series = load_series(str(movie))
    saved = []
    mask_out = tmp_path / "drawn.png"
    get, post = draw_api(ImageSource(series), 0, [str(movie)], mask_out, on_save=saved.append)
    with serving(get, post) as server:
        body = json.dumps(DRAWN).encode()
        status, data, _ = _get(server, "/api/region", method="POST", body=body,
                               headers={"Content-Type": "application/json",
                                        "Origin": f"http://127.0.0.1:{server.server_address[1]}"})
        assert status == 200, data
        ans = json.loads(data)
        # a cross-origin page cannot make it write
        assert _get(server, "/api/region", method="POST", body=body,
                    headers={"Content-Type": "application/json",
                             "Origin": "http://evil.example"})[0] == 403
    assert saved and saved[0]["command"] == ans["command"]
    np.testing.assert_array_equal(read_mask(str(mask_out), (100, 120)), _hand_mask((100, 120)))
    hand = tmp_path / "hand.npy"
    np.save(hand, _hand_mask((100, 120)))
    drawn_run = ans["command"].split()[2:]  # after 'stsdic run'
    drawn_run[drawn_run.index("--out") + 1] = str(tmp_path / "drawn.h5")
    assert main(["run", *drawn_run, *RUN, "--m", "0", "--frames", "0:2", *FAST]) == 0
    assert main(["run", str(movie), "--roi", "12", "18", "106", "84", "--mask", str(hand),
                 "--out", str(tmp_path / "hand.h5"), *RUN, "--m", "0", "--frames", "0:2",
                 *FAST]) == 0
    with h5py.File(tmp_path / "drawn.h5") as a, h5py.File(tmp_path / "hand.h5") as b:
        pa, pb = a["points"][()], b["points"][()]
    np.testing.assert_array_equal(pa, pb)
    assert len(pa) > 10
    inside = _hand_mask((100, 120))[pa[:, 1].astype(int), pa[:, 0].astype(int)]
    assert inside.all()


def test_an_existing_mask_is_not_replaced_without_overwrite(result, tmp_path):
    movie, _ = result
    old = tmp_path / "old.png"
    old.write_bytes(b"keep me")
    get, post = draw_api(ImageSource(load_series(str(movie))), 0, [str(movie)], old)
    with serving(get, post) as server:
        status, data, _ = _get(server, "/api/region", method="POST",
                               body=json.dumps(DRAWN).encode(),
                               headers={"Content-Type": "application/json"})
    assert status == 400 and b"--overwrite" in data
    assert old.read_bytes() == b"keep me"


# ----------------------------------------------------------------------------------------
# the command line
# ----------------------------------------------------------------------------------------


def _start(*argv: str, cwd: Path) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-m", "torch_stsdic", "view", *argv,
                             "--no-browser"], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            env={**__import__("os").environ, "PYTHONPATH": str(ROOT)})
    deadline = time.time() + 120
    url = None
    while time.time() < deadline and url is None:
        line = proc.stdout.readline()
        if not line:
            break
        if "http://127.0.0.1:" in line:
            url = line.split()[0]
    assert url, proc.stderr.read() if proc.poll() is not None else "no address printed"
    return proc, url


@pytest.mark.parametrize("what", ["result", "frames"])
def test_command_prints_a_free_port_and_stops_cleanly_on_ctrl_c(result, tmp_path, what):
    movie, path = result
    proc, url = _start(str(path if what == "result" else movie), cwd=tmp_path)
    try:
        port = int(url.rsplit(":", 1)[1].strip("/"))
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        conn.request("GET", "/api/meta")
        meta = json.loads(conn.getresponse().read())
        conn.close()
        assert meta["mode"] == ("result" if what == "result" else "draw")
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "stopped" in err and "Traceback" not in err
    with pytest.raises(OSError):  # the port is closed
        socket_probe(port)


def socket_probe(port: int) -> None:
    import socket

    with socket.create_connection(("127.0.0.1", port), timeout=2):
        pass


def test_command_errors_are_one_line(capsys, result, tmp_path):
    movie, path = result
    assert main(["view", str(tmp_path / "missing.h5"), "--no-browser"]) == 1
    assert "result file not found" in capsys.readouterr().err
    assert main(["view", str(movie), "--reference", "99", "--no-browser"]) == 2
    assert "--reference 99" in capsys.readouterr().err
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        taken = s.getsockname()[1]
        assert main(["view", str(path), "--port", str(taken), "--no-browser"]) == 1
        err = capsys.readouterr().err
        assert f"cannot serve on 127.0.0.1:{taken}" in err and err.count("\n") == 1


def test_without_no_browser_it_opens_the_page_in_the_browser(capsys, monkeypatch, result):
    """The address printed is the one given to the browser; Ctrl-C (here: a KeyboardInterrupt
    once the browser was asked) ends it with 0."""
    import threading
    import webbrowser

    from torch_stsdic.view.server import ViewServer

    _, path = result
    opened: list[str] = []
    asked = threading.Event()

    def fake_open(url, *a, **k):
        opened.append(url)
        asked.set()
        return True

    def serve(self, poll_interval=0.5):
        assert asked.wait(20)
        raise KeyboardInterrupt

    monkeypatch.setattr(webbrowser, "open", fake_open)
    monkeypatch.setattr(ViewServer, "serve_forever", serve)
    assert main(["view", str(path)]) == 0
    out, err = capsys.readouterr()
    assert opened and opened[0] in out and opened[0].startswith("http://127.0.0.1:")
    assert "stopped" in err


def test_port_option_is_the_port_served(capsys, monkeypatch, result):
    import socket

    from torch_stsdic.view.server import ViewServer

    _, path = result
    with socket.socket() as s:  # a port free a moment ago
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    seen = []

    def serve(self, poll_interval=0.5):
        seen.append(self.server_address)
        raise KeyboardInterrupt

    monkeypatch.setattr(ViewServer, "serve_forever", serve)
    assert main(["view", str(path), "--port", str(port), "--no-browser"]) == 0
    assert seen == [("127.0.0.1", port)]
    assert f"http://127.0.0.1:{port}/" in capsys.readouterr().out
