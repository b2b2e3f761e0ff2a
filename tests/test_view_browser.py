"""``stsdic view`` in a real browser: Debian's Chromium driven by Playwright (headless), the
page's own Content-Security-Policy in force. The page loads, the slider and the keys change
the frame, the pointer shows the file's values, clicks plot histories (the file's numbers),
a file still being written grows, a stereo file shows U, V, W and its shape, and a region
drawn with the mouse saves the mask a hand-typed --roi/--mask run agrees with.

Skipped where Playwright or Chromium is missing (pip install playwright; apt-get install
chromium). Screenshots go to $STSDIC_VIEW_SHOTS when set (else the test's tmp folder)."""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np
import pytest
from view_support import FAST, RUN, chromium, make_result, serving, serving_result, writing

from torch_stsdic.cli import main
from torch_stsdic.core.status import usable
from torch_stsdic.io import load_series, read_mask

sync_api = pytest.importorskip("playwright.sync_api",
                               reason="playwright is not installed (pip install playwright)")
CHROMIUM = chromium()
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no Chromium (apt-get install "
                                "chromium, or set STSDIC_CHROMIUM)")

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="module")
def browser():
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM,
                              args=["--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"])
        yield b
        b.close()


@pytest.fixture
def page(browser, request):
    ctx = browser.new_context(viewport={"width": 1400, "height": 860})
    pg = ctx.new_page()
    problems: list[str] = []
    pg.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    pg.on("console", lambda m: problems.append(f"console {m.type}: {m.text}")
          if m.type == "error" else None)
    pg.problems = problems
    yield pg
    ctx.close()
    assert not problems, problems  # no script error, no refused resource (CSP), no 404


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    return make_result(tmp_path_factory.mktemp("viewb"))


def shot(page, request, name: str) -> Path:
    """A screenshot of the page, in $STSDIC_VIEW_SHOTS or the test's tmp folder."""
    env = os.environ.get("STSDIC_VIEW_SHOTS")
    folder = Path(env) if env else request.getfixturevalue("tmp_path")
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.png"
    page.screenshot(path=str(path))
    assert path.stat().st_size > 10_000
    return path


def until(page, js: str, timeout: float = 15.0):
    """Evaluate ``js`` in the page until it is truthy (the page's CSP forbids Playwright's
    wait_for_function, which evaluates strings); its value."""
    import time

    end = time.time() + timeout
    while True:
        value = page.evaluate(js)
        if value or time.time() > end:
            assert value, f"{js} stayed false for {timeout} s"
            return value
        time.sleep(0.2)


def open_page(page, server) -> None:
    page.goto(server.url)
    page.wait_for_selector("body[data-ready='1']", timeout=30_000)


def client_xy(page, x: float, y: float) -> tuple[float, float]:
    """Page coordinates of image point (x, y) px."""
    cx, cy = page.evaluate(f"window.stsdicView.view.toClient({x}, {y})")
    return cx, cy


def shown_row(page) -> int:
    return int(page.get_attribute("#stage", "data-row"))


def wait_row(page, row: int) -> None:
    page.wait_for_selector(f"#stage[data-row='{row}']", timeout=15_000)


def _file(path: Path) -> dict[str, np.ndarray]:
    with h5py.File(path, "r") as f:
        return {k: f[k][()] for k in f if isinstance(f[k], h5py.Dataset)}


# ----------------------------------------------------------------------------------------


def test_page_loads_slider_and_keys_change_the_frame(page, result, request):
    _, path = result
    d = _file(path)
    valid = usable(d["status"]) & (np.nan_to_num(d["zncc"], nan=-1) >= 0.8)
    with serving_result(path) as server:
        open_page(page, server)
        assert shown_row(page) == 6  # the last finished frame
        assert "frame 6" in page.inner_text("#frame-label")
        assert page.input_value("#field") == "u"
        page.fill("#slider", "4")  # a range input: sets the value, fires 'input'
        wait_row(page, 4)
        assert "frame 4" in page.inner_text("#frame-label")
        assert "frame=4" in page.evaluate("window.stsdicView.img.src")
        shown = np.array(page.evaluate("Array.from(window.stsdicView.values)"), dtype=float)
        np.testing.assert_allclose(shown, np.where(valid[4], d["u"][4], np.nan), rtol=1e-6,
                                   equal_nan=True)
        page.keyboard.press("ArrowRight")
        wait_row(page, 5)
        page.keyboard.press("ArrowLeft")
        page.keyboard.press("ArrowLeft")
        wait_row(page, 3)
        page.click("#play")
        page.wait_for_selector("#stage:not([data-row='3'])", timeout=15_000)
        page.click("#play")
        # the field drawn over the image: coloured pixels at a point's cell
        page.select_option("#field", "exx")
        page.wait_for_selector("#stage[data-field='exx']")
        r = shown_row(page)
        k = int(np.flatnonzero(np.isfinite(np.where(valid[r], d["exx"][r], np.nan)))[0])
        assert page.evaluate("window.stsdicView.lim.label") == "exx (-)"
        pos = page.evaluate(f"Array.from(window.stsdicView.pos.slice({2 * k}, {2 * k + 2}))")
        rgb = page.evaluate(
            "([x, y]) => { const v = window.stsdicView, c = v.canvas;"
            " const [cx, cy] = v.view.toCanvas(x, y), r = window.devicePixelRatio || 1;"
            " return Array.from(c.getContext('2d').getImageData(Math.round(cx * r),"
            " Math.round(cy * r), 1, 1).data); }", pos)
        assert max(rgb[:3]) - min(rgb[:3]) > 20  # a colour, not the grey image
        shot(page, request, "result_2d")


def test_hover_shows_the_point_and_clicks_plot_and_compare_histories(page, result, request):
    _, path = result
    d = _file(path)
    valid = usable(d["status"]) & (np.nan_to_num(d["zncc"], nan=-1) >= 0.8)
    pts = d["points"]
    row = 5
    k, j = int(np.flatnonzero(valid[row])[3]), int(np.flatnonzero(valid[row])[-5])
    with serving_result(path) as server:
        open_page(page, server)
        page.fill("#slider", str(row))
        wait_row(page, row)
        at = [pts[k, 0] + d["u"][row, k], pts[k, 1] + d["v"][row, k]]  # drawn where it moved
        page.mouse.move(*client_xy(page, *at))
        page.wait_for_selector(f"#point-table[data-point='{k}']", timeout=10_000)
        cell = page.inner_text("#point-table tr[data-field='u'] td.num")
        assert float(cell) == pytest.approx(float(d["u"][row, k]), rel=1e-3, abs=1e-4)
        assert float(page.inner_text("#point-table tr[data-field='zncc'] td.num")) == \
            pytest.approx(float(d["zncc"][row, k]), abs=1e-4)
        assert "converged" in page.inner_text("#point-table tr[data-field='status'] td.num") \
            or "max_iter" in page.inner_text("#point-table tr[data-field='status'] td.num")
        assert page.is_visible("#tooltip") and f"#{k} " in page.inner_text("#tooltip")
        page.mouse.click(*client_xy(page, *at))
        page.wait_for_selector(f"#chart[data-points='{k}']", timeout=10_000)
        hist = page.evaluate("window.stsdicView.picks[0].history")
        np.testing.assert_allclose(np.array(hist["values"], dtype=float),
                                   np.where(valid[:, k], d["u"][:, k], np.nan), rtol=1e-6,
                                   equal_nan=True)
        np.testing.assert_allclose(np.array(hist["std"], dtype=float),
                                   np.where(valid[:, k], d["u_std"][:, k], np.nan), rtol=1e-6,
                                   equal_nan=True)
        assert "u_std" in page.inner_text("#legend")
        at2 = [pts[j, 0] + d["u"][row, j], pts[j, 1] + d["v"][row, j]]
        page.mouse.click(*client_xy(page, *at2))
        page.wait_for_selector(f"#chart[data-points='{k},{j}']", timeout=10_000)
        # the chart draws both curves: its pixels hold both pick colours
        colours = page.evaluate(
            "() => { const c = document.getElementById('chart'), g = c.getContext('2d');"
            " const d = g.getImageData(0, 0, c.width, c.height).data; let a = 0, b = 0;"
            " for (let i = 0; i < d.length; i += 4) {"
            "  if (d[i] > 200 && d[i+1] > 140 && d[i+1] < 200 && d[i+2] < 80) a++;"
            "  if (d[i] < 80 && d[i+1] > 180 && d[i+2] > 200) b++; } return [a, b]; }")
        assert min(colours) > 20, colours
        page.mouse.move(*client_xy(page, *at2))
        shot(page, request, "result_2d_histories")
        # a click on the chart picks the frame
        box = page.locator("#chart").bounding_box()
        page.mouse.click(box["x"] + 62, box["y"] + box["height"] / 2)
        wait_row(page, 0)


def test_a_file_still_being_written_grows_in_the_page(page, tmp_path, request):
    path = tmp_path / "live.h5"
    with writing(path) as run, serving_result(path) as server:
        open_page(page, server)
        page.wait_for_selector("#badge[data-finished='2']")
        assert shown_row(page) == 1
        assert "2 of 6 frames finished" in page.inner_text("#badge")
        page.fill("#slider", "3")
        wait_row(page, 3)
        assert "not finished" in page.inner_text("#stage-note")
        run.more(2)
        page.wait_for_selector("#badge[data-finished='4']", timeout=15_000)
        until(page, "!Number.isNaN(window.stsdicView.values[0])")
        assert page.inner_text("#stage-note") == ""
        shown = page.evaluate("Array.from(window.stsdicView.values)")
        pts = np.reshape(page.evaluate("Array.from(window.stsdicView.ref)"), (-1, 2))
        np.testing.assert_allclose(shown, 3 * (1 + pts[:, 0] / 100), rtol=1e-6)
        shot(page, request, "live")


@pytest.fixture(scope="module")
def stereo_h5(tmp_path_factory) -> tuple[Path, Path]:
    """A small 'stsdic stereo' result (the one of test_stereo_export) and its left movie."""
    from test_stereo_export import write_stereo_run  # tests/ on the path

    d = tmp_path_factory.mktemp("stereo_view")
    return write_stereo_run(d), d / "left.tif"


def test_stereo_page_shows_u_v_w_and_the_shape(page, stereo_h5, request):
    path, left = stereo_h5
    d = _file(path)
    ok = usable(d["status"]) & np.isfinite(d["X"])
    row = 4
    k = int(np.flatnonzero(ok[row])[len(np.flatnonzero(ok[row])) // 2])
    with serving_result(path, image=[str(left)]) as server:
        open_page(page, server)
        assert page.input_value("#field") == "W"
        options = page.eval_on_selector_all("#field option", "os => os.map(o => o.value)")
        assert {"U", "V", "W", "Ut", "X", "Z", "reprojection_error"} <= set(options)
        assert page.is_visible("#shape")
        page.fill("#slider", str(row))
        wait_row(page, row)
        xyz = np.reshape(page.evaluate("Array.from(window.stsdicView.xyz)"), (-1, 3))
        np.testing.assert_allclose(xyz[k], [d["X"][row, k], d["Y"][row, k], d["Z"][row, k]],
                                   rtol=1e-6)
        page.mouse.move(*client_xy(page, *d["points"][k]))  # stereo: drawn on the reference
        page.wait_for_selector(f"#point-table[data-point='{k}']", timeout=10_000)
        w = float(page.inner_text("#point-table tr[data-field='W'] td.num"))
        assert w == pytest.approx(float(d["W"][row, k]), rel=1e-3, abs=1e-6)
        label = page.evaluate("window.stsdicView.lim.label")
        assert label == "W (mm)"
        page.mouse.click(*client_xy(page, *d["points"][k]))
        page.wait_for_selector(f"#chart[data-points='{k}']")
        assert "W_std" in page.inner_text("#legend")
        # the shape turns when dragged
        box = page.locator("#shape").bounding_box()
        before = page.evaluate("window.stsdicView.yaw")
        page.mouse.move(box["x"] + 100, box["y"] + 100)
        page.mouse.down()
        page.mouse.move(box["x"] + 160, box["y"] + 120, steps=4)
        page.mouse.up()
        assert page.evaluate("window.stsdicView.yaw") != before
        page.select_option("#field", "U")
        page.wait_for_selector("#stage[data-field='U']")
        shot(page, request, "stereo")


# ----------------------------------------------------------------------------------------
# drawing the region
# ----------------------------------------------------------------------------------------


def _hand_mask(shape) -> np.ndarray:
    m = np.zeros(shape, dtype=bool)
    m[22:79, 15:101] = True  # the region polygon, its outline included
    m[40:56, 40:71] = False  # the hole, its outline left out
    return m


def test_region_drawn_with_the_mouse_runs_like_the_same_roi_and_mask_typed(page, result,
                                                                          tmp_path, request):
    from torch_stsdic.view.server import draw_api
    from torch_stsdic.view.source import ImageSource

    movie, _ = result
    mask_out = tmp_path / "drawn.png"
    get, post = draw_api(ImageSource(load_series(str(movie))), 0, [str(movie)], mask_out)
    with serving(get, post) as server:
        open_page(page, server)
        # the box: a drag (the page snaps to pixel centres)
        page.mouse.move(*client_xy(page, 12.2, 17.8))
        page.mouse.down()
        page.mouse.move(*client_xy(page, 60, 50), steps=3)
        page.mouse.move(*client_xy(page, 105.8, 84.3), steps=3)
        page.mouse.up()
        page.keyboard.press("r")
        for x, y in ((15, 22), (100, 22), (100, 78), (15, 78)):
            page.mouse.click(*client_xy(page, x + 0.3, y - 0.3))
        page.keyboard.press("Enter")
        page.keyboard.press("h")
        for x, y in ((40, 40), (70, 40), (70, 55), (40, 55)):
            page.mouse.click(*client_xy(page, x, y))
        page.keyboard.press("Enter")
        page.click("#save")
        page.wait_for_selector("#save-note[data-saved='1']")
        command = page.input_value("#command")
        shot(page, request, "draw")
    assert "--roi 12 18 106 84" in command and f"--mask {mask_out}" in command
    np.testing.assert_array_equal(read_mask(str(mask_out), (100, 120)), _hand_mask((100, 120)))
    hand = tmp_path / "hand.png"
    from PIL import Image

    Image.fromarray(_hand_mask((100, 120)).astype(np.uint8) * 255).save(hand)
    words = command.split()[2:]
    words[words.index("--out") + 1] = str(tmp_path / "drawn.h5")
    common = [*RUN, "--m", "0", "--frames", "0:2", *FAST]
    assert main(["run", *words, *common]) == 0
    assert main(["run", str(movie), "--roi", "12", "18", "106", "84", "--mask", str(hand),
                 "--out", str(tmp_path / "hand.h5"), *common]) == 0
    a, b = _file(tmp_path / "drawn.h5"), _file(tmp_path / "hand.h5")
    np.testing.assert_array_equal(a["points"], b["points"])
    assert len(a["points"]) > 10


# ----------------------------------------------------------------------------------------
# the hourglass (muDIC), where ../shared/data has it
# ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def hourglass(tmp_path_factory) -> Path:
    src = DATA / "mudic-hourglass"
    if not src.is_dir():
        pytest.skip(f"{src} is absent (the muDIC hourglass images)")
    out = tmp_path_factory.mktemp("hourglass") / "hourglass.h5"
    assert main(["run", str(src), "--roi", "150", "20", "1120", "734", "--subset", "31",
                 "--step", "60", "--m", "1", "--frames", "0:4", "--out", str(out), *FAST]) == 0
    return out


def test_hourglass_result_page(page, hourglass, request):
    d = _file(hourglass)
    valid = usable(d["status"]) & (np.nan_to_num(d["zncc"], nan=-1) >= 0.8)
    row = 3
    k = int(np.flatnonzero(valid[row])[len(np.flatnonzero(valid[row])) // 2])
    with serving_result(hourglass) as server:
        open_page(page, server)
        assert page.evaluate("window.stsdicView.meta.image") is not None  # the images found
        page.fill("#slider", str(row))
        wait_row(page, row)
        page.select_option("#field", "v")
        page.wait_for_selector("#stage[data-field='v']")
        at = [d["points"][k, 0] + d["u"][row, k], d["points"][k, 1] + d["v"][row, k]]
        page.mouse.move(*client_xy(page, *at))
        page.wait_for_selector(f"#point-table[data-point='{k}']", timeout=10_000)
        v = float(page.inner_text("#point-table tr[data-field='v'] td.num"))
        assert v == pytest.approx(float(d["v"][row, k]), rel=1e-3, abs=1e-3)
        page.mouse.click(*client_xy(page, *at))
        page.wait_for_selector(f"#chart[data-points='{k}']")
        shot(page, request, "hourglass")


def test_controls_without_images(page, result, request):
    """No image (--no-image): the points' extent is drawn; the status field gets its codes'
    colours, typed limits are used as typed, the reference configuration draws the points
    where they were, a lower min ZNCC shows more points."""
    _, path = result
    d = _file(path)
    with serving_result(path, no_image=True) as server:
        open_page(page, server)
        assert page.evaluate("window.stsdicView.meta.image") is None
        page.select_option("#field", "status")
        page.wait_for_selector("#stage[data-field='status']")
        assert page.evaluate("window.stsdicView.lim.cmap") == "status"
        shown = page.evaluate("Array.from(window.stsdicView.values)")
        np.testing.assert_array_equal(shown, d["status"][shown_row(page)])
        page.select_option("#field", "v")
        page.wait_for_selector("#stage[data-field='v']")
        page.click("#scope button[data-scope='frame']")
        until(page, "window.stsdicView.lim && window.stsdicView.lim.rows === 1")
        page.fill("#lim-lo", "-0.5")
        page.fill("#lim-hi", "0.25")
        page.press("#lim-hi", "Enter")
        until(page, "window.stsdicView.scope === 'manual'")
        assert page.evaluate("[window.stsdicView.limits().lo, window.stsdicView.limits().hi]") \
            == [-0.5, 0.25]
        page.click("#cfg-ref")
        until(page, "window.stsdicView.deformed === false")
        k = 7
        page.mouse.move(*client_xy(page, *d["points"][k]))  # at its reference position
        page.wait_for_selector(f"#point-table[data-point='{k}']", timeout=10_000)
        page.fill("#min-zncc", "-1")
        page.press("#min-zncc", "Enter")
        until(page, "window.stsdicView.minZncc === -1")
        page.set_viewport_size({"width": 1100, "height": 700})
        page.click("text=fit view")
        shot(page, request, "no_image_manual_limits")
