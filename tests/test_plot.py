"""Tests of torch_stsdic.plot: figures are built, saved as non-empty PNGs, NaN-safe."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from torch_stsdic.plot import (  # noqa: E402
    plot_error_vs_noise,
    plot_field,
    plot_fields,
    plot_history,
    plot_xy,
)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def grid_points(nx=8, ny=6, step=10.0, x0=15.0, y0=12.0):
    xs, ys = np.meshgrid(x0 + step * np.arange(nx), y0 + step * np.arange(ny))
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


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
    assert len(fig.axes) == 2  # field + colour bar
    ax = fig.axes[0]
    assert ax.get_ylim()[0] > ax.get_ylim()[1]  # y down
    assert ax.get_xlim() == pytest.approx((-0.5, 109.5))
    assert fig.axes[1].get_ylabel() == "u (px)"
    assert_png(tmp_path / "a" / "u.png")


def test_plot_field_scattered_no_image_torch_input(tmp_path):
    rng = np.random.default_rng(1)
    pts = torch.as_tensor(rng.uniform(0, 100, (50, 2)))
    vals = torch.as_tensor(rng.normal(size=50))
    vals[3] = float("nan")
    fig = plot_field(None, pts, vals, cmap="RdBu_r", symmetric=True, path=tmp_path / "s.png")
    assert len(fig.axes) == 2
    assert len(fig.axes[0].collections) == 1
    assert fig.axes[0].collections[0].get_offsets().shape[0] == 49  # NaN point left out
    assert_png(tmp_path / "s.png")


def test_plot_field_all_nan_and_holes(tmp_path, image):
    pts = grid_points()[::2]  # holes
    fig = plot_field(image, pts, np.full(len(pts), np.nan), path=tmp_path / "nan.png")
    assert len(fig.axes) == 2
    assert_png(tmp_path / "nan.png")
    with pytest.raises(ValueError, match="values"):
        plot_field(image, pts, np.zeros(3))


def test_plot_fields_panels(tmp_path, image):
    pts = grid_points()
    n = len(pts)
    fields = {k: np.linspace(-1, 1, n) * (i + 1) for i, k in enumerate(["u", "v", "exx", "eyy"])}
    fields["exy"] = np.full(n, np.nan)
    fig = plot_fields(image, pts, fields, tmp_path / "fields.png", suptitle="frame 3", dpi=60)
    assert len(fig.axes) == 2 * len(fields)  # one colour bar per panel, spare panel removed
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
    assert out is fig and len(fig.axes) == 3
