"""Figures that cannot mislead (issue 34, item 2): every mean over points shows how many
points it rests on and is left out where they are too few; panel notes fit their panels; an
incomplete result file says so on the figures and in the summary, and its 'last' frame is not
the reference."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402

import torch_stsdic.plot as plot_module  # noqa: E402
from torch_stsdic.cli import main  # noqa: E402
from torch_stsdic.core.status import Status  # noqa: E402
from torch_stsdic.io.results import ResultWriter  # noqa: E402
from torch_stsdic.plot import plot_fields, plot_history  # noqa: E402


def write_result(path, *, nx=8, ny=8, n_frames=12, done=None, few=(), m_zero=0.0):
    """A result file of a steady motion u = 0.1 t on an nx x ny grid: rows ``done`` finished
    (default all), at frames ``few`` all points but 2 unusable (those 2 wild), and a share
    ``m_zero`` of the points classical (m = 0, no velocity)."""
    xs, ys = np.meshgrid(10.0 + 10 * np.arange(nx), 10.0 + 10 * np.arange(ny))
    pts = np.stack([xs.ravel(), ys.ravel()], 1)
    n = len(pts)
    frames = np.arange(n_frames)
    fields = ("u", "v", "ut", "vt", "zncc", "status")
    w = ResultWriter(path, points=pts, frames=frames, times=frames.astype(float),
                     config={"track": {"reference": 0}}, inputs=[], fields=fields,
                     extra_fields=("m",))
    rows = frames if done is None else np.asarray(done)
    k_zero = int(round(m_zero * n))
    for r in rows:
        u = np.full(n, 0.1 * r)
        status = np.zeros(n, np.int8)
        if r in few:
            status[2:] = int(Status.POOR_FIT)
            u[:2] = -5.0  # two wild points
        ut = np.full(n, 0.1)
        m = np.full(n, 2, np.int8)
        m[:k_zero] = 0
        ut[:k_zero] = np.nan
        w.write_rows([r], {"u": u, "v": np.zeros(n), "ut": ut, "vt": np.where(np.isnan(ut),
                           np.nan, 0.0), "zncc": np.full(n, 0.99), "status": status, "m": m})
    w.close()
    return path


@pytest.fixture
def saved(monkeypatch):
    """Every figure the plot module saves: {file name: figure}."""
    figs = {}
    real = plot_module.save_figure

    def keep(fig, path, **kw):
        if path is not None:
            figs[path.name] = fig
        return real(fig, path, **kw)

    monkeypatch.setattr(plot_module, "save_figure", keep)
    return figs


def _titles(fig):
    out = [fig._suptitle.get_text()] if fig._suptitle is not None else []
    return out + [ax.get_title() for ax in fig.axes]


def test_mean_history_shows_its_points_and_leaves_out_too_few(tmp_path, capsys, saved):
    res = write_result(tmp_path / "r.h5", few=(8, 9))
    assert main(["plot", str(res), "--out", str(tmp_path / "p"), "--no-image"]) == 0
    out = capsys.readouterr().out
    assert "history_mean.png: frame(s) 8, 9 left out" in out, out
    assert "fewer than 20 of 64 points" in out, out
    fig = saved["history_mean.png"]
    main_ax, count_ax = fig.axes[:2]
    u = main_ax.lines[0].get_ydata()
    assert np.isnan(u[[8, 9]]).all() and np.isfinite(u[:8]).all()  # a gap, not -5 px
    counts = count_ax.lines[0].get_ydata()
    np.testing.assert_array_equal(counts[[7, 8, 9]], [64, 2, 2])
    assert "usable points" in count_ax.get_ylabel()
    assert "velocity_history_mean.png: frame(s) 8, 9 left out" in out


def test_history_counts_in_the_library():
    t = np.arange(6.0)
    fig = plot_history(t, {"u": t * 0.1}, counts=[50, 50, 3, 50, 0, 50], min_count=10)
    y = fig.axes[0].lines[0].get_ydata()
    np.testing.assert_array_equal(np.isnan(y), [False, False, True, False, True, False])
    assert len(fig.axes) == 2
    with pytest.raises(ValueError, match="counts"):
        plot_history(t, {"u": t}, counts=[1, 2])


def test_incomplete_file_says_so_and_last_is_not_the_reference(tmp_path, capsys, saved):
    res = write_result(tmp_path / "r.h5", done=[0, 1, 2])
    assert main(["plot", str(res), "--out", str(tmp_path / "p"), "--no-image"]) == 0
    out = capsys.readouterr().out
    assert "incomplete: 3 of 12 frames finished" in out and "--resume" in out, out
    assert (tmp_path / "p" / "fields_frame00002.png").exists()
    for name in ("fields_frame00002.png", "quality_frame00002.png", "history_mean.png"):
        assert any("incomplete" in t.lower() for t in _titles(saved[name])), name


def test_only_the_reference_finished_is_not_plotted_as_last(tmp_path, capsys):
    res = write_result(tmp_path / "r.h5", done=[0])
    code = main(["plot", str(res), "--out", str(tmp_path / "p"), "--no-image"])
    err = capsys.readouterr().err
    assert code == 1
    assert "only the reference frame is finished" in err and "1 of 12" in err, err
    assert not (tmp_path / "p" / "fields_frame00000.png").exists()
    # asked for by number it is drawn, and the figure says the file is incomplete
    assert main(["plot", str(res), "--out", str(tmp_path / "p"), "--no-image",
                 "--frame", "0"]) == 0


def test_complete_file_has_no_incomplete_note(tmp_path, capsys, saved):
    res = write_result(tmp_path / "r.h5")
    assert main(["plot", str(res), "--out", str(tmp_path / "p"), "--no-image"]) == 0
    assert "incomplete" not in capsys.readouterr().out
    assert not any("incomplete" in t.lower() for f in saved.values() for t in _titles(f))
    assert (tmp_path / "p" / "fields_frame00011.png").exists()


def _extent(fig, artist):
    return artist.get_window_extent(FigureCanvasAgg(fig).get_renderer())


@pytest.mark.parametrize("shape", [(4, 40), (40, 4), (10, 10)], ids=["tall", "wide", "square"])
def test_panel_notes_fit_their_panels(shape):
    """A velocity panel's note stays over its own panel and colour bar, never over the next
    panel (a tall specimen puts the panels side by side, narrow)."""
    nx, ny = shape
    xs, ys = np.meshgrid(np.arange(nx) * 10.0, np.arange(ny) * 10.0)
    pts = np.stack([xs.ravel(), ys.ravel()], 1)
    vals = {nm: pts[:, 0] * 0.01 for nm in ("u", "v", "ut", "vt")}
    from torch_stsdic.cli.plot import velocity_note

    note = velocity_note(np.r_[np.zeros(10), np.full(len(pts) - 10, 2)], np.ones(len(pts), bool))
    fig = plot_fields(None, pts, vals, notes={"ut": note, "vt": note})
    FigureCanvasAgg(fig).draw()
    panels = [ax for ax in fig.axes if ax.child_axes]
    width = fig.get_size_inches()[0] * fig.dpi
    assert sum("\n" in ax.get_title() for ax in panels) == 2
    for ax in panels:
        title = _extent(fig, ax.title)
        assert 0 <= title.x0 and title.x1 <= width, (ax.get_title(), title, width)
        for other in (o for o in panels if o is not ax):
            for box in (_extent(fig, other), _extent(fig, other.child_axes[0])):
                assert not title.overlaps(box), (ax.get_title(), other.get_title())
