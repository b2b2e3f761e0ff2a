"""Tests of torch_stsdic.plot: figures are built, saved as non-empty PNGs, NaN-safe."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from torch_stsdic.core.status import Status  # noqa: E402
from torch_stsdic.io import Units  # noqa: E402
from torch_stsdic.plot import (  # noqa: E402
    animate_field,
    is_diverging,
    panel_layout,
    plot_error_vs_noise,
    plot_field,
    plot_fields,
    plot_history,
    plot_status,
    plot_xy,
)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def grid_points(nx=8, ny=6, step=10.0, x0=15.0, y0=12.0):
    xs, ys = np.meshgrid(x0 + step * np.arange(nx), y0 + step * np.arange(ny))
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def colorbars(fig):
    """The colour-bar axes of a figure (insets beside their panels)."""
    return [c for ax in fig.axes for c in ax.child_axes]


def panels(fig):
    """(axes, its colour-bar axes) of every panel that has one."""
    return [(ax, ax.child_axes[0]) for ax in fig.axes if ax.child_axes]


def assert_png(path):
    data = path.read_bytes()
    assert len(data) > 1000 and data[:8] == PNG_MAGIC


@pytest.fixture
def image():
    return np.random.default_rng(0).random((90, 110))


def test_plot_field_grid_over_image_with_nans(tmp_path, image):
    pts = grid_points()
    vals = pts[:, 0] * 0.01
    vals[::5] = np.nan
    fig = plot_field(image, pts, vals, title="u", label="u (px)", path=tmp_path / "a" / "u.png")
    assert isinstance(fig, Figure)
    assert len(fig.axes) == 1 and len(colorbars(fig)) == 1  # field + its colour bar
    ax = fig.axes[0]
    assert ax.get_ylim()[0] > ax.get_ylim()[1]  # y down
    assert ax.get_xlim() == pytest.approx((-0.5, 109.5))
    assert colorbars(fig)[0].get_ylabel() == "u (px)"
    assert_png(tmp_path / "a" / "u.png")


def test_plot_field_scattered_no_image_torch_input(tmp_path):
    rng = np.random.default_rng(1)
    pts = torch.as_tensor(rng.uniform(0, 100, (50, 2)))
    vals = torch.as_tensor(rng.normal(size=50))
    vals[3] = float("nan")
    fig = plot_field(None, pts, vals, cmap="RdBu_r", symmetric=True, path=tmp_path / "s.png")
    assert len(colorbars(fig)) == 1
    assert len(fig.axes[0].collections) == 1
    assert fig.axes[0].collections[0].get_offsets().shape[0] == 49  # NaN point left out
    assert_png(tmp_path / "s.png")


def test_plot_field_all_nan_and_holes(tmp_path, image):
    pts = grid_points()[::2]  # holes
    fig = plot_field(image, pts, np.full(len(pts), np.nan), path=tmp_path / "nan.png")
    assert len(colorbars(fig)) == 1
    assert_png(tmp_path / "nan.png")
    with pytest.raises(ValueError, match="values"):
        plot_field(image, pts, np.zeros(3))


def test_plot_fields_panels(tmp_path, image):
    pts = grid_points()
    n = len(pts)
    fields = {k: np.linspace(-1, 1, n) * (i + 1) for i, k in enumerate(["u", "v", "exx", "eyy"])}
    fields["exy"] = np.full(n, np.nan)
    fig = plot_fields(image, pts, fields, tmp_path / "fields.png", suptitle="frame 3", dpi=60)
    assert len(fig.axes) == len(fields) == len(colorbars(fig))  # spare panel removed
    titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
    assert titles == list(fields)
    assert_png(tmp_path / "fields.png")
    with pytest.raises(ValueError):
        plot_fields(image, pts, {})


def test_plot_history_and_xy(tmp_path):
    t = np.arange(20.0)
    u = 0.1 * t
    u_dic = u + np.random.default_rng(2).normal(0, 0.02, 20)
    u_dic[7] = np.nan
    fig = plot_history(
        t, {"true": u, "DIC": u_dic, "STS m=2": u}, ylabel="u (px)", path=tmp_path / "h.png"
    )
    assert len(fig.axes) == 1 and len(fig.axes[0].lines) == 3
    assert fig.axes[0].get_legend() is not None
    assert_png(tmp_path / "h.png")

    fig = plot_xy([1, 2, 3, 4], {"m": [0.1, 0.05, 0.04, np.nan]}, xlabel="m", logy=True)
    assert fig.axes[0].get_yscale() == "log"
    with pytest.raises(ValueError, match="shape"):
        plot_xy([1, 2], {"bad": [1, 2, 3]})


def test_plot_error_vs_noise(tmp_path):
    sig = np.array([0.0, 2.0, 4.0, 8.0])
    fig = plot_error_vs_noise(
        sig,
        {"DIC": [0.002, 0.01, 0.02, 0.04], "STS": [0.001, 0.005, 0.01, 0.02]},
        path=tmp_path / "e.png",
    )
    assert len(fig.axes) == 1 and len(fig.axes[0].lines) == 2
    assert "noise" in fig.axes[0].get_xlabel()
    assert_png(tmp_path / "e.png")


def test_plot_field_into_existing_axes():
    fig = Figure()
    axs = fig.subplots(1, 2)
    out = plot_field(None, grid_points(), np.arange(48.0), ax=axs[1], label="x")
    assert out is fig and len(fig.axes) == 2 and len(axs[1].child_axes) == 1


def test_colour_bars_are_as_tall_as_their_panels_on_a_tall_specimen(tmp_path):
    """Sample 12 (a 1040 x 400 px plate): the colour bars used to be taller than the panels
    and the five panels filled a third of the width."""
    image = np.random.default_rng(3).random((1040, 400))
    pts = grid_points(nx=25, ny=90, step=10.0, x0=60.0, y0=60.0)
    fields = {k: np.linspace(-1, 1, len(pts)) * 1e-3 for k in ("u", "v", "exx", "eyy", "exy")}
    fig = plot_fields(image, pts, fields, tmp_path / "tall.png", units=Units(0.02, "mm"))
    fig.canvas.draw()
    axes = [ax for ax, _ in panels(fig)]
    assert len(axes) == 5 and len({round(ax.get_position().y0, 3) for ax in axes}) == 1  # 1 row
    for ax, cax in panels(fig):
        a, c = ax.get_position(), cax.get_position()
        assert c.height == pytest.approx(a.height, rel=1e-3) and c.y0 == pytest.approx(a.y0)
    # the panels fill the page: a third of its area (0.13 with the former 3 x 2 layout)
    drawn = sum(ax.get_position().width * ax.get_position().height for ax in axes)
    assert drawn > 0.25
    labels = [cax.get_ylabel() for _, cax in panels(fig)]
    assert labels == ["u (mm)", "v (mm)", "exx (-)", "eyy (-)", "exy (-)"]
    assert panel_layout(5, 400 / 1040)[:2] == (1, 5) and panel_layout(5, 1.0)[:2] == (2, 3)
    assert panel_layout(4, 1.0)[:2] == (2, 2)  # balanced rows, no empty half row


def test_shared_and_diverging_limits(image):
    pts = grid_points()
    a = np.linspace(-0.01, 0.03, len(pts))
    fields = {"u error, A": a, "u error, B": a / 3, "u": a + 1.0}
    fig = plot_fields(image, pts, fields, share=[["u error, A", "u error, B"]])
    norms = {ax.get_title(): ax.images[-1].norm for ax in fig.axes}
    na, nb = norms["u error, A"], norms["u error, B"]
    assert (na.vmin, na.vmax) == (nb.vmin, nb.vmax)  # shared: compared by eye
    assert na.vmin == -na.vmax > 0 or na.vmin == -na.vmax  # centred on 0
    assert fig.axes[0].images[-1].get_cmap().name == "RdBu_r"
    assert norms["u"].vmin > 0.98 and fig.axes[2].images[-1].get_cmap().name == "viridis"
    assert is_diverging("exx") and is_diverging("u error") and not is_diverging("u")


def test_status_map_names_every_code(tmp_path, image):
    pts = grid_points()
    status = np.zeros(len(pts), dtype=np.int8)
    status[:12] = int(Status.DIVERGED)
    fig = plot_status(image, pts, status, path=tmp_path / "st.png")
    ticks = [t.get_text() for t in colorbars(fig)[0].get_yticklabels()]
    assert len(ticks) == len(Status)
    assert "converged 75.0 %" in ticks and "diverged 25.0 %" in ticks
    assert_png(tmp_path / "st.png")


def test_animation_is_a_gif_with_one_frame_per_row(tmp_path, image):
    from PIL import Image

    pts = grid_points()
    vals = np.stack([np.full(len(pts), k, dtype=np.float64) for k in range(4)])
    vals[1, :5] = np.nan
    out = animate_field(lambda k: image, pts, vals, tmp_path / "m.mp4", label="u (px)",
                        displacement=(vals * 0 + 1.0, vals * 0), stamps=[f"frame {k}"
                                                                        for k in range(4)])
    assert out.suffix in (".gif", ".mp4")
    if out.suffix == ".gif":
        assert Image.open(out).n_frames == 4
    with pytest.raises(ValueError, match="shape"):
        animate_field(None, pts, vals[:, :3], tmp_path / "bad.gif")


def test_legend_of_many_curves_does_not_cover_the_axes():
    t = np.arange(9.0)
    fig = plot_xy(t, {f"method {k}": t * k for k in range(4)})
    fig.canvas.draw()
    ax = fig.axes[0]
    leg = ax.get_legend().get_window_extent()
    assert leg.y1 <= ax.get_window_extent().y0  # under the axes


def test_stsdic_plot_in_the_recorded_units(tmp_path, monkeypatch):
    """``stsdic plot`` on a file calibrated 0.5 um/px with times in s: colour bars and axes
    say um, um/s and s; a quality map and the --animate GIF are written."""
    import torch_stsdic.plot as tplot
    from torch_stsdic.cli import main
    from torch_stsdic.io import ResultWriter

    pts = grid_points(nx=5, ny=4)
    names = ("u", "v", "ut", "vt", "zncc", "status", "exx", "eyy", "exy")
    path = tmp_path / "c.h5"
    with ResultWriter(path, points=pts, frames=[0, 1, 2], times=[0.0, 0.5, 1.0], config={},
                      inputs=[], fields=names,
                      attrs={"scale": 0.5, "unit": "um", "time_unit": "s"}) as w:  # fmt: skip
        for r in range(3):
            vals = {nm: np.linspace(-1, 1, len(pts)) * (r + 1) for nm in names}
            vals["zncc"] = np.full(len(pts), 0.99)
            vals["status"] = np.zeros(len(pts), dtype=np.int8)
            w.write_rows([r], vals)
    figs = {}
    for name in ("plot_fields", "plot_history"):
        real = getattr(tplot, name)

        def spy(*a, _real=real, _name=name, **k):
            fig = _real(*a, **k)
            figs.setdefault(_name, []).append(fig)
            return fig

        monkeypatch.setattr(tplot, name, spy)
    out = tmp_path / "plots"
    assert main(["plot", str(path), "--out", str(out), "--animate", "u", "--dpi", "40"]) == 0
    names_out = {p.name for p in out.iterdir()}
    assert {"fields_frame00002.png", "quality_frame00002.png", "u_movie.gif",
            "history_mean.png", "velocity_history_mean.png"} <= names_out  # fmt: skip
    labels = [c.get_ylabel() for c in colorbars(figs["plot_fields"][0])]
    assert labels == ["u (um)", "v (um)", "exx (-)", "eyy (-)", "exy (-)"]
    u_map = figs["plot_fields"][0].axes[0].images[-1].get_array()
    assert float(u_map.max()) == pytest.approx(3.0 * 0.5)  # last frame: 3 px = 1.5 um
    # the time axis is labelled under the lowest panel (the points each mean rests on)
    hist = {f.axes[0].get_ylabel(): f.axes[-1].get_xlabel() for f in figs["plot_history"]}
    assert hist["displacement (um)"] == "time (s)" and "velocity (um/s)" in hist
    assert main(["plot", str(path), "--out", str(out), "--animate", "nope"]) == 2
